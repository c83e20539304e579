"""Reading a dataset's text file, with the one-line errors every importer gives."""

from __future__ import annotations


def read_ascii(path: str, error: type[ValueError]) -> str:
    """The text of an ASCII file (universal newlines); a missing, unreadable or non-ASCII file is an
    ``error`` (the importer's own error type) naming the file."""
    try:
        with open(path, encoding="ascii") as f:
            return f.read()
    except FileNotFoundError:
        raise error(f"{path}: no such file") from None
    except UnicodeDecodeError:
        raise error(f"{path}: not an ASCII text file") from None
    except OSError as e:
        raise error(f"{path}: cannot read: {e.strerror or e}") from None
