"""``python -m aumesh``: the same as the ``aumesh`` command (what the DVC stages run)."""

from aumesh.cli import run

run()
