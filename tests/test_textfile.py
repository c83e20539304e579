"""The importers' one-line errors for a file they cannot read (``hybridslam.datasets.textfile``)."""

from __future__ import annotations

import pytest

from hybridslam.datasets.kitti_files import KITTIError, read_tum
from hybridslam.datasets.mrclam_files import MRCLAMError, read_table


def _kitti(path: str) -> None:
    read_tum(path)


def _mrclam(path: str) -> None:
    read_table(path, 3, "time, x, y")


@pytest.mark.parametrize("read, error", [(_kitti, KITTIError), (_mrclam, MRCLAMError)], ids=["kitti", "mrclam"])
def test_a_file_that_cannot_be_read_is_one_error_naming_it(tmp_path, read, error):
    latin = tmp_path / "latin.txt"
    latin.write_bytes(b"1 2 3\n\xe9t\xe9\n")
    cases = {tmp_path / "missing.txt": "no such file", latin: "not an ASCII text file",
             tmp_path: "cannot read: Is a directory"}
    for path, what in cases.items():
        with pytest.raises(error) as e:
            read(str(path))
        assert str(e.value) == f"{path}: {what}"


def test_line_numbers_count_every_line(tmp_path):
    """Comments and blank lines count, and Windows line ends are lines like any other."""
    path = tmp_path / "table.dat"
    path.write_bytes(b"# header\r\n\r\n1 2 3\r\n4 5\r\n")
    with pytest.raises(MRCLAMError, match=r"table.dat:4: expected 3 numbers \(time, x, y\), got '4 5'"):
        _mrclam(str(path))
    path.write_bytes(b"# header\r\n\r\n1 2 3\r\n")
    table = read_table(str(path), 3, "time, x, y")
    assert table.lines.tolist() == [3]
