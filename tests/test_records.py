"""The record file of a study survives kills, garbage, a full disk and a second study on its folder.

`Records` is exercised directly with small fake records (no JAX compiles); the faults are
injected by writing damaged files, by monkeypatching ``os.write`` / ``os.fsync`` / ``os.ftruncate``,
by a real file-size limit in a child process (the kernel's own short write), and by real second
processes for the lock.
"""

from __future__ import annotations

import errno
import json
import os
import re
import signal
import subprocess
import sys
import textwrap

import pytest

from hybridslam.cli import main as cli_main
from hybridslam.studies import records as rec
from hybridslam.studies import study

HEADER = {"study": "test", "tracks": 3}
HEAD_LINE = json.dumps({"format": rec.RECORD_FORMAT, **HEADER}) + "\n"
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def record(alpha: float) -> dict:
    return {"cell": {"alpha": alpha, "model": "mirror"}, "metrics": {"entropy": [[0.5, float("nan")]]}}


def line(alpha: float) -> str:
    return json.dumps(record(alpha), allow_nan=True) + "\n"


def cells(records: rec.Records) -> list[float]:
    return sorted(r["cell"]["alpha"] for r in records.done.values())


def records_file(folder) -> str:
    return os.path.join(str(folder), rec.RECORDS)


def write(folder, text: str | bytes) -> None:
    data = text.encode() if isinstance(text, str) else text
    with open(records_file(folder), "wb") as f:
        f.write(data)


def read(folder) -> bytes:
    with open(records_file(folder), "rb") as f:
        return f.read()


def python(code: str, **kwargs) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [ROOT, os.environ.get("PYTHONPATH")])))
    return subprocess.Popen([sys.executable, "-c", textwrap.dedent(code)], env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, **kwargs)


# --------------------------------------------------------------------------- #
# Resumption
# --------------------------------------------------------------------------- #


def test_study_keeps_its_public_names():
    for name in ("Records", "StudyError", "read_table", "RECORDS", "RECORD_FORMAT"):
        assert getattr(study, name) is getattr(rec, name)


def test_a_new_folder_gets_a_header_and_a_reopened_one_resumes(tmp_path):
    with rec.Records(str(tmp_path), HEADER) as r:
        assert r.done == {} and read(tmp_path) == HEAD_LINE.encode()
        r.append(record(0.1))
        r.append(record(0.4))
    assert read(tmp_path) == (HEAD_LINE + line(0.1) + line(0.4)).encode()
    with rec.Records(str(tmp_path), HEADER) as r:
        assert cells(r) == [0.1, 0.4]
        assert {"model": "mirror", "alpha": 0.4} in r and {"alpha": 0.7, "model": "mirror"} not in r
        r.append(record(0.7))
    with rec.Records(str(tmp_path), HEADER) as r:
        assert cells(r) == [0.1, 0.4, 0.7]


def test_records_made_with_other_settings_are_refused(tmp_path):
    with rec.Records(str(tmp_path), HEADER) as r:
        r.append(record(0.1))
    before = read(tmp_path)
    with pytest.raises(rec.StudyError, match=r"holds a study with other settings \(tracks: 3 there, 5 now\); "
                                             r"use another output folder, or the same settings to resume it"):
        rec.Records(str(tmp_path), {**HEADER, "tracks": 5})
    assert read(tmp_path) == before
    rec.Records(str(tmp_path), HEADER).close()  # the refused one let go of the lock


# --------------------------------------------------------------------------- #
# Damaged files
# --------------------------------------------------------------------------- #


def test_a_cut_off_last_line_is_dropped(tmp_path, capsys):
    write(tmp_path, HEAD_LINE + line(0.1) + line(0.4)[:17])
    with rec.Records(str(tmp_path), HEADER) as r:
        assert cells(r) == [0.1]
        assert read(tmp_path) == (HEAD_LINE + line(0.1)).encode()
        r.append(record(0.4))
    assert read(tmp_path) == (HEAD_LINE + line(0.1) + line(0.4)).encode()
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "dropped a cut-off last line" in err and "its cell runs again" in err


@pytest.mark.parametrize("garbage", [
    b"garbage\n",
    line(0.4)[:17].encode() + b"\n",  # a partly flushed buffer
    b'{"metrics": {}}\n',  # valid JSON, no cell
    b'{"cell": 0.4}\n',  # a cell that is no object
    b"[1, 2]\n",
    b"\x00\x00\x00\x00\n",
    b"\xff\xfe{\n",  # not even UTF-8
    b"\n",
], ids=["text", "cut-json", "no-cell", "cell-not-object", "list", "zeros", "not-utf8", "empty"])
def test_a_garbled_last_line_is_dropped(tmp_path, capsys, garbage):
    write(tmp_path, HEAD_LINE.encode() + line(0.1).encode() + garbage)
    with rec.Records(str(tmp_path), HEADER) as r:
        assert cells(r) == [0.1]
        r.append(record(0.4))
    assert read(tmp_path) == (HEAD_LINE + line(0.1) + line(0.4)).encode()
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "dropped a garbled last line (line 3)" in err


def test_a_garbled_line_and_a_cut_off_one_after_it_are_dropped_with_one_message(tmp_path, capsys):
    write(tmp_path, HEAD_LINE + line(0.1) + "garbage\n" + line(0.4)[:20])
    with rec.Records(str(tmp_path), HEADER) as r:
        assert cells(r) == [0.1]
    assert read(tmp_path) == (HEAD_LINE + line(0.1)).encode()
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "a garbled last line (line 3) and a cut-off line after it" in err


def test_fields_a_record_must_have(tmp_path, capsys):
    write(tmp_path, HEAD_LINE + line(0.1) + json.dumps({"cell": {"alpha": 0.4}}) + "\n")
    with rec.Records(str(tmp_path), HEADER, fields=("metrics",)) as r:
        assert cells(r) == [0.1]
    assert "garbled last line" in capsys.readouterr().err


@pytest.mark.parametrize(("bad", "problem"), [
    ("garbage\n", "is not valid JSON"),
    ('{"metrics": {}}\n', "lacks 'cell'"),
    ("\n", "is empty"),
])
def test_a_bad_line_before_the_last_is_an_error_naming_it(tmp_path, bad, problem):
    write(tmp_path, HEAD_LINE + line(0.1) + bad + line(0.4))
    before = read(tmp_path)
    message = (rf"{re.escape(records_file(tmp_path))}: line 3 {problem}; the lines after it hold finished "
               r"cells, so it is no interrupted write: repair or delete that line to resume$")
    for _ in range(2):  # the lock was let go: the second attempt says the same
        with pytest.raises(rec.StudyError, match=message):
            rec.Records(str(tmp_path), HEADER)
    assert read(tmp_path) == before  # finished work is never dropped


def test_a_cut_off_or_garbled_header_alone_starts_afresh(tmp_path, capsys):
    for damaged, said in [(HEAD_LINE[:10], "a cut-off header"), ("{garbage\n", "a garbled header"),
                          ("", None)]:
        write(tmp_path, damaged)
        with rec.Records(str(tmp_path), HEADER) as r:
            assert r.done == {}
        assert read(tmp_path) == HEAD_LINE.encode()
        err = capsys.readouterr().err
        assert (said in err and "the header is written afresh" in err) if said else err == ""


def test_a_garbled_header_before_records_is_an_error(tmp_path):
    write(tmp_path, "{garbage\n" + line(0.1))
    with pytest.raises(rec.StudyError, match="line 1 is not a sweep header; remove the file to start afresh"):
        rec.Records(str(tmp_path), HEADER)


# --------------------------------------------------------------------------- #
# A full disk
# --------------------------------------------------------------------------- #


def half_then(error: OSError | None):
    """An ``os.write`` that writes half of what it is given, then raises ``error`` (or returns short)."""
    real = os.write

    def write(fd: int, data: bytes) -> int:
        n = real(fd, data[: len(data) // 2])
        if error is not None:
            raise error
        return n

    return write


FULL = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


@pytest.mark.parametrize(("failure", "reason", "fix"), [
    (("write", half_then(FULL)), "no space left on device", "free space"),
    (("write", half_then(None)), r"short write \(\d+ of \d+ bytes; disk full\?\)", "free space"),
    (("fsync", None), "input/output error", "fix the cause"),
], ids=["enospc", "short-write", "fsync-eio"])
def test_a_failed_append_leaves_the_file_as_it_was(tmp_path, monkeypatch, failure, reason, fix):
    name, replacement = failure
    if name == "fsync":
        def replacement(fd):
            raise OSError(errno.EIO, os.strerror(errno.EIO))
    r = rec.Records(str(tmp_path), HEADER)
    r.append(record(0.1))
    before = read(tmp_path)
    with monkeypatch.context() as m:
        m.setattr(os, name, replacement)
        with pytest.raises(rec.RecordWriteError) as info:
            r.append(record(0.4))
    message = str(info.value)
    assert re.fullmatch(
        rf'{reason} while recording cell {{"alpha": 0.4, "model": "mirror"}} in '
        rf"{re.escape(records_file(tmp_path))}; nothing was lost: {fix} and run the same command again "
        r"to resume", message), message
    assert isinstance(info.value, rec.StudyError) and isinstance(info.value.__cause__, OSError)
    assert read(tmp_path) == before and cells(r) == [0.1]
    r.close()
    with rec.Records(str(tmp_path), HEADER) as again:  # the same command again resumes
        assert cells(again) == [0.1]
        again.append(record(0.4))
    with rec.Records(str(tmp_path), HEADER) as again:
        assert cells(again) == [0.1, 0.4]


def test_an_append_that_cannot_be_undone_refuses_more_and_the_next_run_drops_it(tmp_path, monkeypatch,
                                                                                capsys):
    r = rec.Records(str(tmp_path), HEADER)
    r.append(record(0.1))

    def no_truncate(fd, length):
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    with monkeypatch.context() as m:
        m.setattr(os, "write", half_then(FULL))
        m.setattr(os, "ftruncate", no_truncate)
        with pytest.raises(rec.RecordWriteError, match="the part written could not be removed"):
            r.append(record(0.4))
    with pytest.raises(rec.RecordWriteError, match="no space left on device while recording"):
        r.append(record(0.7))  # a line after the cut-off part would be a damaged middle line
    r.close()
    assert not read(tmp_path).endswith(b"\n")
    with rec.Records(str(tmp_path), HEADER) as again:
        assert cells(again) == [0.1]
    assert "dropped a cut-off last line" in capsys.readouterr().err


def test_a_full_disk_while_writing_the_header(tmp_path, monkeypatch):
    with monkeypatch.context() as m:
        m.setattr(os, "write", half_then(FULL))
        with pytest.raises(rec.RecordWriteError, match="no space left on device while writing the header"):
            rec.Records(str(tmp_path), HEADER)
    assert read(tmp_path) == b""
    with rec.Records(str(tmp_path), HEADER) as r:  # the lock was let go; the empty file gets its header
        assert r.done == {}
    assert read(tmp_path) == HEAD_LINE.encode()


COLUMNS = ("alpha", "step", "entropy")
ROWS = [{"alpha": 0.1, "step": k, "entropy": 0.5 * k} for k in range(1, 4)]


def test_a_failed_table_rewrite_keeps_the_old_table(tmp_path, monkeypatch):
    path = str(tmp_path / "table.csv")
    rec.write_table(path, COLUMNS, ROWS)
    old = rec.read_table(path)
    assert [r["step"] for r in old] == ["1", "2", "3"]

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with monkeypatch.context() as m:
        m.setattr(os, "fsync", full)
        with pytest.raises(rec.RecordWriteError) as info:
            rec.write_table(path, COLUMNS, ROWS * 2)
    assert str(info.value) == (
        f"no space left on device while writing {path}; the previous table is intact and every finished "
        "cell is in cells.jsonl: free space and run the same command again")
    assert rec.read_table(path) == old and os.listdir(tmp_path) == ["table.csv"]
    with pytest.raises(KeyError):  # not a write failure: raised as it is, and still no temporary file
        rec.write_table(path, COLUMNS, [{"alpha": 0.1}])
    assert rec.read_table(path) == old and os.listdir(tmp_path) == ["table.csv"]


def test_a_real_short_write_under_a_file_size_limit(tmp_path):
    """The kernel's own partial writes: RLIMIT_FSIZE lets a write through up to the limit only."""
    child = python(f"""
        import json, os, resource, signal
        from hybridslam.studies import records as rec
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG and short writes instead of a signal
        folder = {str(tmp_path)!r}
        table = os.path.join(folder, "table.csv")
        rows = [{{"alpha": 0.1, "step": k}} for k in range(3)]
        rec.write_table(table, ("alpha", "step"), rows)
        r = rec.Records(folder, {HEADER!r})
        r.append({{"cell": {{"alpha": 0.1}}}})
        size = os.path.getsize(r.path)
        resource.setrlimit(resource.RLIMIT_FSIZE, (size + 10, resource.RLIM_INFINITY))
        out = {{}}
        try:
            r.append({{"cell": {{"alpha": 0.4}}, "padding": "x" * 100}})
        except rec.RecordWriteError as e:
            out["append"] = str(e)
        try:
            rec.write_table(table, ("alpha", "step"), rows * 1000)
        except rec.RecordWriteError as e:
            out["table"] = str(e)
        out["size"], out["kept"] = size, os.path.getsize(r.path)
        print(json.dumps(out))
    """)
    stdout, stderr = child.communicate(timeout=120)
    assert child.returncode == 0, stderr
    out = json.loads(stdout)
    assert out["kept"] == out["size"]
    assert re.match(r"short write \(10 of \d+ bytes; disk full\?\) while recording cell", out["append"]), out
    assert out["table"].startswith("file too large while writing "), out
    assert rec.read_table(str(tmp_path / "table.csv")) == [{"alpha": "0.1", "step": str(k)} for k in range(3)]
    assert sorted(os.listdir(tmp_path)) == ["cells.jsonl", "cells.jsonl.lock", "table.csv"]


# --------------------------------------------------------------------------- #
# Two studies on one folder
# --------------------------------------------------------------------------- #


def busy(folder, pid: int) -> str:
    return (rf"^another study \(pid {pid}, started at \d{{4}}-\d\d-\d\d \d\d:\d\d:\d\d.*\) is writing to "
            rf"{re.escape(str(folder))}; wait for it or use another -o folder$")


def test_a_second_records_on_the_folder_is_refused_until_the_first_closes(tmp_path):
    first = rec.Records(str(tmp_path), HEADER)
    with pytest.raises(rec.StudyBusyError, match=busy(tmp_path, os.getpid())):
        rec.Records(str(tmp_path), HEADER)
    with pytest.raises(rec.StudyBusyError):  # the lock comes before the header: any study is refused
        rec.Records(str(tmp_path), {"other": "settings"})
    first.close()
    with rec.Records(str(tmp_path), HEADER) as second:
        with pytest.raises(rec.StudyBusyError):
            rec.Records(str(tmp_path), HEADER)
        second.append(record(0.1))
    with rec.Records(str(tmp_path), HEADER) as third:  # the context manager let go
        assert cells(third) == [0.1]
    with pytest.raises(rec.StudyError, match="closed"):
        third.append(record(0.4))


def test_the_sweep_command_refuses_a_folder_in_use(tmp_path, capsys):
    with rec.Records(str(tmp_path), HEADER):
        assert cli_main(["sweep", "--alphas", "0.1", "--models", "mirror", "-o", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert re.fullmatch(busy(tmp_path, os.getpid()).replace("^", "^hybridslam: error: "), err), err


def test_the_lock_holds_across_processes_and_dies_with_its_holder(tmp_path):
    code = f"""
        import sys
        from hybridslam.studies import records as rec
        try:
            r = rec.Records({str(tmp_path)!r}, {HEADER!r})
        except rec.StudyBusyError as e:
            sys.exit(str(e))
        print("locked", flush=True)
        sys.stdin.read()
    """
    with rec.Records(str(tmp_path), HEADER):  # this process holds it: the child is refused
        child = python(code, stdin=subprocess.PIPE)
        _, stderr = child.communicate(timeout=120)
        assert child.returncode == 1 and re.fullmatch(busy(tmp_path, os.getpid()), stderr.strip()), stderr
    child = python(code, stdin=subprocess.PIPE)  # the child holds it: this process is refused
    try:
        assert child.stdout.readline() == "locked\n", child.stderr.read()
        with pytest.raises(rec.StudyBusyError, match=busy(tmp_path, child.pid)):
            rec.Records(str(tmp_path), HEADER)
    finally:
        child.send_signal(signal.SIGKILL)
        child.communicate(timeout=60)
    with rec.Records(str(tmp_path), HEADER) as r:  # the kernel let go with the killed holder
        r.append(record(0.1))


def test_only_process_0_writes_or_locks(tmp_path, monkeypatch):
    write(tmp_path, HEAD_LINE + line(0.1) + "garbage\n" + line(0.4)[:9])
    before = read(tmp_path)
    monkeypatch.setattr(rec, "is_writer", lambda: False)
    with rec.Records(str(tmp_path), HEADER) as a, rec.Records(str(tmp_path), HEADER) as b:
        assert cells(a) == cells(b) == [0.1]  # what process 0 keeps, without touching the file
        a.append(record(0.7))
        assert cells(a) == [0.1, 0.7]
    assert read(tmp_path) == before and not os.path.exists(os.path.join(tmp_path, rec.LOCK))
