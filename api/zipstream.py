"""A ZIP archive of files written as it is sent: never built in memory or on disk.

Python's ``zipfile`` writes to a stream it cannot seek (each entry's sizes and CRC follow its data in a data
descriptor, ZIP64 where an entry needs it), so the archive is produced chunk by chunk from the files it names:
memory holds one chunk. Already compressed files (GeoTIFF, PNG) are stored, text is deflated.
"""

from __future__ import annotations

import zipfile
from collections.abc import Iterable, Iterator
from pathlib import Path

CHUNK = 1024 * 1024
STORED_SUFFIXES = frozenset({".tif", ".tiff", ".png", ".jpg", ".jpeg", ".zip", ".npz"})


class _Pipe:
    """The unseekable file ``zipfile`` writes to: it keeps what was written until ``take`` hands it on."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.offset = 0

    def write(self, data: bytes) -> int:
        self.parts.append(bytes(data))
        self.offset += len(data)
        return len(data)

    def tell(self) -> int:  # zipfile asks where it is, to record each entry's offset
        return self.offset

    def flush(self) -> None:
        return None

    def take(self) -> bytes:
        data, self.parts = b"".join(self.parts), []
        return data


def zip_chunks(entries: Iterable[tuple[str, Path | bytes]]) -> Iterator[bytes]:
    """The bytes of a ZIP archive of ``entries`` (name in the archive, a file or the bytes themselves), in
    chunks of about ``CHUNK``.

    A file that vanished since it was listed is left out (a job deleted meanwhile); the names are the caller's,
    never a server path.
    """
    pipe = _Pipe()
    with zipfile.ZipFile(pipe, "w", allowZip64=True) as archive:  # type: ignore[call-overload]
        for name, path in entries:
            if isinstance(path, bytes):
                archive.writestr(name, path, compress_type=zipfile.ZIP_DEFLATED)
                yield pipe.take()
                continue
            try:
                source = path.open("rb")
            except FileNotFoundError:
                continue
            with source:
                info = zipfile.ZipInfo.from_file(path, name)  # its size decides whether the entry needs ZIP64
                stored = path.suffix.lower() in STORED_SUFFIXES
                info.compress_type = zipfile.ZIP_STORED if stored else zipfile.ZIP_DEFLATED
                with archive.open(info, "w") as entry:
                    while chunk := source.read(CHUNK):
                        entry.write(chunk)
                        if data := pipe.take():
                            yield data
            if data := pipe.take():
                yield data
    if data := pipe.take():  # the central directory
        yield data
