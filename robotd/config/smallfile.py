"""Read a small regular file (a configuration, a key) without ever blocking or reading without bound.

A path given by a user may name a FIFO (opening it blocks until a writer appears), a device such as /dev/zero
(endless), or a directory. The file is examined with stat() before it is opened, opened with O_NONBLOCK so even a
FIFO swapped in meanwhile cannot block, checked again on the open descriptor, and read up to a limit.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

_KINDS = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


class SmallFileError(Exception):
    """The file cannot be used; the message says why, without the path."""


class MissingFileError(SmallFileError):
    """There is no file at that path."""


def kind(mode: int) -> str:
    """What a file of this st_mode is, in words ("a directory")."""
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


def regular_file(path: str | Path) -> os.stat_result:
    """The status of `path` (symbolic links followed), or SmallFileError when it is missing or not a regular file."""
    try:
        info = os.stat(path)
    except FileNotFoundError as error:
        raise MissingFileError(error.strerror or str(error)) from None
    except OSError as error:
        raise SmallFileError(error.strerror or str(error)) from None
    except ValueError as error:  # an embedded NUL byte
        raise SmallFileError(str(error)) from None
    if not stat.S_ISREG(info.st_mode):
        raise SmallFileError(f"is {kind(info.st_mode)}, not a regular file")
    return info


def read_small_file(path: str | Path, limit: int) -> bytes:
    """The content of the regular file `path`, at most `limit` bytes, or SmallFileError saying why not."""
    info = regular_file(path)
    if info.st_size > limit:
        raise SmallFileError(f"holds {info.st_size} bytes, more than the {limit} allowed")
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except OSError as error:
        raise SmallFileError(error.strerror or str(error)) from None
    try:
        opened = os.fstat(fd)
        if not stat.S_ISREG(opened.st_mode):  # replaced between stat() and open()
            raise SmallFileError(f"is {kind(opened.st_mode)}, not a regular file")
        chunks: list[bytes] = []
        size = 0
        while size <= limit:
            chunk = os.read(fd, limit + 1 - size)
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
    except OSError as error:
        raise SmallFileError(error.strerror or str(error)) from None
    finally:
        os.close(fd)
    if size > limit:  # grew since stat()
        raise SmallFileError(f"holds more than the {limit} bytes allowed")
    return b"".join(chunks)
