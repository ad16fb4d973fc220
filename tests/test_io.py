"""Row I/O on .npy files (aumesh.core.io), checked against NumPy's own reader and writer."""

from __future__ import annotations

import numpy as np
import pytest

from aumesh.core.io import NpyRowFile, NpyRows, create_npy, read_row_set, read_rows, row_runs, write_rows


@pytest.mark.parametrize("dtype, row_shape", [(np.float32, (1434,)), (np.float64, (3, 5)), (np.int64, ())])
def test_row_file_writes_and_reads_what_numpy_does(tmp_path, dtype, row_shape):
    rng = np.random.default_rng(0)
    expected = (rng.normal(size=(37, *row_shape)) * 100).astype(dtype)
    path = tmp_path / "rows.npy"
    create_npy(path, dtype, expected.shape)
    with NpyRowFile(path, writable=True) as f:  # blocks out of order, one open file
        for lo in (20, 0, 7, 33):
            hi = {0: 7, 7: 20, 20: 33, 33: 37}[lo]
            f.write(lo, expected[lo:hi])
    np.testing.assert_array_equal(np.load(path), expected)
    with NpyRowFile(path) as f:
        np.testing.assert_array_equal(f.read(5, 19), expected[5:19])
        out = np.empty((40, *row_shape), dtype=dtype)
        np.testing.assert_array_equal(f.read(30, 50, out), expected[30:])  # clipped to the file, into out's head
    np.testing.assert_array_equal(read_rows(path, 3, 4), expected[3:4])
    rows = np.array([9, 2, 2, 36, 10, 11, 0])
    np.testing.assert_array_equal(read_row_set(path, rows), expected[rows])
    np.testing.assert_array_equal(NpyRows(path)[rows], expected[rows])


def test_write_rows_into_a_numpy_saved_file(tmp_path):
    path = tmp_path / "saved.npy"
    np.save(path, np.zeros((6, 4)))
    write_rows(path, 2, np.full((2, 4), 7.0))
    np.testing.assert_array_equal(np.load(path)[:, 0], [0, 0, 7, 7, 0, 0])


def test_truncated_file_is_named(tmp_path):
    path = tmp_path / "cut.npy"
    np.save(path, np.arange(40.0).reshape(10, 4))
    size = path.stat().st_size
    with open(path, "r+b") as fh:
        fh.truncate(size - 3 * 32)  # three rows short
    with pytest.raises(EOFError, match=r"cut\.npy: truncated at row 7"):
        read_rows(path, 0, 10)


def test_row_runs_split_sorted_rows_at_gaps():
    assert row_runs(np.array([], dtype=int)) == []
    assert row_runs(np.array([3, 4, 5, 9, 11, 12])) == [(0, (3, 6)), (3, (9, 10)), (4, (11, 13))]


def test_take_reads_rows_in_the_order_asked(tmp_path):
    """NpyRowFile.take: rows in any order (runs of consecutive rows, jumps back and forth, repeats), as numpy's
    fancy indexing of the loaded array gives them, into a caller's buffer."""
    data = np.random.default_rng(3).normal(size=(40, 7)).astype(np.float32)
    np.save(tmp_path / "a.npy", data)
    rows = np.r_[10:14, 0:3, 30:32, 5, 5, 39, 20:25]
    out = np.full((len(rows) + 3, 7), np.nan, np.float32)
    with NpyRowFile(tmp_path / "a.npy") as f:
        got = f.take(rows, out)
        np.testing.assert_array_equal(f.take(rows[::-1]), data[rows[::-1]])
    np.testing.assert_array_equal(got, data[rows])
    assert np.shares_memory(got, out) and np.isnan(out[len(rows) :]).all()


@pytest.mark.parametrize("reader", ["load_npy", "load_npz", "npy_layout"])
def test_npy_reads_in_threads_never_parse_two_headers_at_once(tmp_path, reader):
    """numpy parses .npy headers with ast.literal_eval, and CPython 3.11 keeps the AST constructor's recursion
    depth in interpreter-wide state (python/cpython#106905): a second thread's parse inside a first one's makes
    the first raise "SystemError: AST constructor recursion depth mismatch" (a prepare on the threads scheduler
    failed so in CI). Here the interleaving is forced: every collection inside thread A's parse (threshold 1)
    hands over to thread B, which reads another file while A waits (up to 50 ms; B waits for the lock instead
    when there is one). Without the lock, A's read fails."""
    import gc
    import sys
    import threading

    from aumesh.core import io as aio

    np.save(tmp_path / "a.npy", np.arange(3.0))
    np.save(tmp_path / "b.npy", np.zeros((2, 5), np.float32))
    np.savez(tmp_path / "a.npz", x=np.arange(3.0), y=np.ones((2, 2)))
    np.savez(tmp_path / "b.npz", x=np.zeros(4), y=np.ones(1))

    def read(name):
        aio._parse_npy_header.cache_clear()  # parse the header every call
        return {
            "load_npy": lambda: aio.load_npy(tmp_path / f"{name}.npy"),
            "load_npz": lambda: aio.load_npz(tmp_path / f"{name}.npz", ["x", "y"]),
            "npy_layout": lambda: aio.npy_layout(tmp_path / f"{name}.npy"),
        }[reader]()

    go, done, stop = threading.Event(), threading.Event(), threading.Event()
    handovers, errors = [0], []

    def thread_b():
        while go.wait() and not stop.is_set():
            go.clear()
            read("b")
            done.set()

    def handover(phase, info):  # runs in whichever thread allocates when a collection starts
        caller = sys._getframe(1).f_code
        if (
            phase == "start"
            and threading.current_thread() is a
            and caller.co_name == "parse"
            and caller.co_filename.endswith("ast.py")
            and handovers[0] < 20
        ):
            handovers[0] += 1
            done.clear()
            go.set()
            done.wait(0.05)

    def thread_a():
        try:
            return read("a")
        except SystemError as e:
            errors.append(e)

    b = threading.Thread(target=thread_b)
    a = threading.Thread(target=thread_a)
    threshold = gc.get_threshold()
    b.start()
    gc.callbacks.append(handover)
    gc.set_threshold(1)
    try:
        a.start()
        a.join()
    finally:
        gc.set_threshold(*threshold)
        gc.callbacks.remove(handover)
        stop.set()
        go.set()
        b.join()
    assert handovers[0] > 0, "no collection happened inside a header parse: the test forced nothing"
    assert not errors, errors


def test_write_row_map_puts_each_row_at_its_number_in_runs(tmp_path, monkeypatch):
    """Rows given by number, in any order and with gaps, land at their numbers; one write per run of consecutive
    numbers; an empty map writes nothing."""
    path = tmp_path / "rows.npy"
    create_npy(path, np.float64, (20, 3))
    rows = {int(r): np.full(3, float(r)) for r in (7, 2, 3, 4, 15, 9, 8)}
    writes = []
    real_write = NpyRowFile.write
    monkeypatch.setattr(
        NpyRowFile,
        "write",
        lambda self, first, block: (writes.append((first, len(block))), real_write(self, first, block)),
    )
    with NpyRowFile(path, writable=True) as f:
        f.write_row_map(rows)
        f.write_row_map({})
    expected = np.zeros((20, 3))
    for r, row in rows.items():
        expected[r] = row
    np.testing.assert_array_equal(np.load(path), expected)
    assert writes == [(2, 3), (7, 3), (15, 1)]
