"""Sequential file I/O around the page cache (``O_DIRECT``) for the store's shard objects.

A shard object is written once by its job and read once by the integrity check or the release; neither
reads it again, so its pages in the page cache are only a cost: the kernel CPU to find, fill and reclaim
them (docs/explanation/library-paths.md measures it).  Both classes fall back to ordinary I/O, with the
same bytes, where a file system refuses ``O_DIRECT``.
"""

from __future__ import annotations

import errno
import fcntl
import mmap
import os
from pathlib import Path


class DirectReader:
    """Read one file sequentially with ``O_DIRECT`` (around the page cache, as :class:`DirectWriter` wrote
    it): ``blocks()`` yields it buffer by buffer without a copy (`object_sha256`), ``read(n)`` is a binary file
    object's (the release tars the store with it, which would otherwise pay the kernel ~21-29 s of CPU for the
    page-cache pages of the store it reads once; docs/explanation/library-paths.md).  Two page-aligned buffers of
    ``DirectWriter.BUFFER`` bytes, the next one read by a thread while the caller uses this one (``readv``
    releases the GIL); the tail after a short read (end of file, unaligned) and any file system that refuses
    ``O_DIRECT`` (at the open or the first read) go by ordinary reads."""

    def __init__(self, path: str | Path):
        from concurrent.futures import ThreadPoolExecutor

        self._path, self._fd, self._file = Path(path), -1, None
        self._bufs = [mmap.mmap(-1, DirectWriter.BUFFER) for _ in range(2)]
        self._views = [memoryview(b) for b in self._bufs]
        self._cur, self._start, self._end = 0, 0, 0  # unread bytes: views[cur][start:end]
        self._done = 0  # file bytes read into the buffers so far
        self._pool, self._ahead = ThreadPoolExecutor(1), None
        try:
            self._fd = os.open(self._path, os.O_RDONLY | os.O_DIRECT)
        except (AttributeError, OSError) as e:
            if isinstance(e, OSError) and e.errno != errno.EINVAL:
                raise
            self._file = open(self._path, "rb")

    def _buffered_from(self, offset: int) -> None:
        os.close(self._fd)
        self._fd = -1
        self._file = open(self._path, "rb")
        self._file.seek(offset)

    def _fill(self) -> None:
        """Make the next buffer current (read ahead, or now); after a short read the rest goes buffered."""
        nxt = 1 - self._cur if self._ahead is not None else self._cur
        try:
            n = self._ahead.result() if self._ahead is not None else os.readv(self._fd, [self._bufs[nxt]])
        except OSError as e:
            if e.errno != errno.EINVAL:
                raise
            self._ahead = None
            self._buffered_from(self._done)  # the flag was taken but the I/O refused
            return
        self._ahead = None
        self._cur, self._start, self._end = nxt, 0, n
        self._done += n
        if n == DirectWriter.BUFFER:
            self._ahead = self._pool.submit(os.readv, self._fd, [self._bufs[1 - nxt]])
        else:  # end of file (or a short read): anything after it, buffered
            self._buffered_from(self._done)

    def blocks(self):
        """The file's bytes as consecutive memoryviews, each valid until the next one is asked for."""
        while True:
            if self._start < self._end:
                view = self._views[self._cur][self._start : self._end]
                self._start = self._end
                try:
                    yield view
                finally:
                    view.release()  # the buffer is read into again, and closing it needs no view left
            elif self._file is not None:
                yield from iter(lambda: self._file.read(DirectWriter.BUFFER), b"")
                return
            else:
                self._fill()

    def read(self, size: int = -1) -> bytes:
        out, got = [], 0
        while size is None or size < 0 or got < size:
            if self._start < self._end:
                k = self._end - self._start if size is None or size < 0 else min(size - got, self._end - self._start)
                out.append(bytes(self._views[self._cur][self._start : self._start + k]))
                self._start += k
                got += k
            elif self._file is not None:
                out.append(self._file.read(-1 if size is None or size < 0 else size - got))
                break
            else:
                self._fill()
        return b"".join(out)

    def close(self) -> None:
        if self._ahead is not None:
            self._ahead.exception()  # let the read in flight finish before its buffer goes
            self._ahead = None
        self._pool.shutdown()
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
        if self._file is not None:
            self._file.close()
        for v, b in zip(self._views, self._bufs):
            if not b.closed:
                v.release()
                b.close()

    def __enter__(self) -> DirectReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class DirectWriter:
    """Write one new file sequentially with ``O_DIRECT``: around the page cache
    (docs/explanation/library-paths.md), for the shard objects, which no job reads back.

    Buffered writes of a 1.84 GB shard cost the writing process seconds of kernel CPU for page-cache pages
    (more when memory is full and the kernel must reclaim to find them) and leave the pages cached; here the
    bytes go through one page-aligned ``mmap`` buffer of ``BUFFER`` bytes (a whole-buffer ``write`` each
    time it fills) straight to the disk.  ``close()`` writes the last partial buffer padded with zeros to
    ``ALIGN`` bytes and truncates the file to the bytes given: the file holds exactly what was written.  A
    file system that refuses ``O_DIRECT`` (``EINVAL`` at the open or the first write: tmpfs before Linux 6.6,
    some network and FUSE file systems) gets the same bytes by ordinary writes (``direct`` is then False).
    """

    BUFFER = 8 << 20
    #: O_DIRECT's alignment of buffer address, file offset and length (>= any logical block size here)
    ALIGN = 4096

    def __init__(self, path: str | Path):
        flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC
        self.direct = hasattr(os, "O_DIRECT")
        try:
            self._fd = os.open(path, flags | (os.O_DIRECT if self.direct else 0), 0o666)
        except OSError as e:
            if e.errno != errno.EINVAL:
                raise
            self.direct = False
            self._fd = os.open(path, flags, 0o666)
        self._buf = mmap.mmap(-1, self.BUFFER)
        self._view = memoryview(self._buf)
        self._pos = 0
        self.size = 0

    def write(self, data) -> int:
        src = memoryview(data).cast("B")
        n, i = len(src), 0
        while i < n:
            k = min(n - i, self.BUFFER - self._pos)
            self._view[self._pos : self._pos + k] = src[i : i + k]
            self._pos += k
            i += k
            if self._pos == self.BUFFER:
                self._flush(self.BUFFER)
        self.size += n
        return n

    def _flush(self, n: int) -> None:
        done = 0
        while done < n:
            try:
                done += os.write(self._fd, self._view[done:n])
            except OSError as e:
                if e.errno != errno.EINVAL or not self.direct or done:
                    raise
                # the file system took the open flag but refuses the I/O: the same bytes, buffered
                fcntl.fcntl(self._fd, fcntl.F_SETFL, fcntl.fcntl(self._fd, fcntl.F_GETFL) & ~os.O_DIRECT)
                self.direct = False
        self._pos = 0

    def close(self) -> None:
        if self._fd < 0:
            return
        try:
            tail = self._pos
            if tail:
                n = -(-tail // self.ALIGN) * self.ALIGN if self.direct else tail
                self._view[tail:n] = bytes(n - tail)
                self._flush(n)
                if n != tail:  # drop the zero padding
                    os.ftruncate(self._fd, self.size)
        finally:
            os.close(self._fd)
            self._fd = -1
            self._view.release()
            self._buf.close()

    def __del__(self) -> None:
        if getattr(self, "_fd", -1) >= 0:
            self.close()

    def __enter__(self) -> DirectWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
