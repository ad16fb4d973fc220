"""README "Working as a team", step 1 without `sudo`: the fenced blocks run as written, as an unprivileged user.

The password block and the no-sudo PostgreSQL block are taken from the README (the blocks that create
``~/.mlflow-db-password`` and run ``initdb``), the port 5432 replaced by a free one and ``~`` by a temporary home, and
run with bash as a user that is not root (PostgreSQL refuses root: the ``postgres`` system user when the test runs as
root, as tests/test_team_postgres.py does). Then the role ``mlflow`` logs in to database ``mlflow`` over TCP with the
password from ``~/.pgpass`` alone, nothing asked (stdin closed).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

from conftest import free_port
from test_team_postgres import PG_BIN, _as_unprivileged

pytestmark = [pytest.mark.slow, pytest.mark.server]

REPO = Path(__file__).resolve().parents[1]


def team_section_blocks() -> list[str]:
    """The ```bash blocks of the README's "Working as a team" section, in order."""
    text = (REPO / "README.md").read_text()
    section = text.split("\n## Working as a team\n", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```bash\n(.*?)```", section, flags=re.S)


def test_the_readme_no_sudo_database_block_runs_as_written(tmp_path):
    blocks = team_section_blocks()
    (password,) = [b for b in blocks if "~/.mlflow-db-password" in b and "initdb" not in b and "sudo" not in b]
    (own_cluster,) = [b for b in blocks if "initdb" in b]
    assert "sudo" not in own_cluster and "--pwprompt" not in own_cluster
    if not (PG_BIN / "initdb").exists():
        pytest.fail(f"{PG_BIN}/initdb not found: install Debian's postgresql (apt-get install -y postgresql)")
    port = str(free_port())
    home = Path(tempfile.mkdtemp(prefix="aumesh-readme-pg-"))  # /tmp/...: the postgres user reaches it
    script = home / "steps.sh"
    script.write_text(
        "set -euo pipefail\n"
        + (password + own_cluster).replace("5432", port).replace("/usr/lib/postgresql/15/bin", str(PG_BIN))
    )
    sudo = _as_unprivileged()
    if sudo:
        shutil.chown(home, user=sudo[2])
        shutil.chown(script, user=sudo[2])
    # libpq finds ~/.pgpass through the user's passwd entry, not $HOME: name the temporary home's file
    env = {k: v for k, v in os.environ.items() if not k.startswith("PG")} | {"HOME": str(home)}
    pgpass = f"PGPASSFILE={home / '.pgpass'}"
    try:
        proc = subprocess.run(
            [*sudo, "env", f"HOME={home}", pgpass, "bash", str(script)],
            cwd=home,
            env=env,
            stdin=subprocess.DEVNULL,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert proc.returncode == 0, proc.stdout + proc.stderr
        assert (home / ".pgpass").stat().st_mode & 0o077 == 0  # libpq ignores a .pgpass others can read
        login = subprocess.run(
            [*sudo, "env", f"HOME={home}", pgpass, str(PG_BIN / "psql"), "-w", "-h", "localhost", "-p", port]
            + ["-U", "mlflow"]
            + ["-d", "mlflow", "-tAc", "select current_user, current_database()"],
            env=env,
            stdin=subprocess.DEVNULL,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert login.returncode == 0 and login.stdout.strip() == "mlflow|mlflow", login.stdout + login.stderr
    finally:
        subprocess.run(
            [*sudo, str(PG_BIN / "pg_ctl"), "-D", str(home / "mlflow-db"), "-m", "fast", "-w", "stop"],
            capture_output=True,
        )
        shutil.rmtree(home, ignore_errors=True)
