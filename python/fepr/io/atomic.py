"""Files that are never half-written: write to a temporary name in the same folder, then rename.

A reader (or a run resumed after a crash) sees either the previous file or the complete new one: ``os.replace``
is atomic on POSIX and Windows when both names are in the same folder.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterator, Union

__all__ = ["atomic_path"]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


#: The permissions a plainly created file gets here (``mkstemp`` makes its file private: 0600).
_FILE_MODE = 0o666 & ~_umask()


@contextlib.contextmanager
def atomic_path(path: Union[str, os.PathLike], suffix: str = "") -> Iterator[str]:
    """A temporary path next to ``path`` to write to; renamed onto ``path`` when the block ends without an
    exception, removed otherwise. The temporary name is ``.<name>.<random>.part<suffix>``: ``suffix`` for writers
    that choose the format by the extension."""
    target = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part" + suffix, dir=target.parent or ".")
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, _FILE_MODE)
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
