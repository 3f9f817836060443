"""Getting MERL .binary files onto disk, verified: download, copy/link from a local directory.

Every file is checked the same way before it is kept: size, header and finite values
(`neumat.io.merl.read_merl`), then the pinned sha256 when one is given. A file that fails is
deleted (for a link: the link, never its target), so a bad download is never mistaken for a
good one; a user's own local files are never modified.
"""

from __future__ import annotations

import hashlib
import http.client
import logging
import os
import shutil
import socket
import time
import urllib.error
import urllib.request
from pathlib import Path

from neumat.io import merl
from neumat.logs import InputError

log = logging.getLogger(__name__)
OFFLINE_HINT = ("Offline or the server is gone? Set `merl.source: local` with `merl.local_dir` "
                "pointing at a directory of <name>.binary files, or run the offline "
                "synthetic config: --configfile config/tiny.yaml")


class ChecksumError(InputError, ValueError):
    """A file whose sha256 differs from the pinned one."""


class DownloadError(InputError, RuntimeError):
    """A file that could not be fetched."""


def sha256_of(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def verify(path: str | os.PathLike, sha256: str | None = None, name: str | None = None,
           remove_bad: bool = True) -> None:
    """Raise MerlFormatError (size, header, NaN) or ChecksumError (sha256 given and different).

    With `remove_bad` the failing file (or link) is deleted. `name` is what the message calls
    the file (e.g. the material when `path` is a temporary download)."""
    path = Path(path)
    name = name or path.name
    try:
        if sha256:  # hash first: cheaper than parsing, and the message most users need
            actual = sha256_of(path)
            if actual != sha256.lower():
                kept = f"{path} removed" if remove_bad else f"{path} left in place"
                raise ChecksumError(
                    f"{name}: sha256 mismatch: expected {sha256.lower()}, got {actual} ({kept}). "
                    "If the file is right and the pinned value is not, set "
                    f"merl.sha256_override: {{{Path(name).stem}: {actual}}}")
        merl.check_negative(name, merl.read_merl(path))  # many negative bins: refused
    except (ChecksumError, merl.MerlFormatError) as e:
        if remove_bad:
            path.unlink(missing_ok=True)
        if isinstance(e, merl.MerlFormatError) and name != str(path):
            raise merl.MerlFormatError(str(e).replace(str(path), name)) from e
        raise


def download(url: str, dest: str | os.PathLike, sha256: str | None = None, retries: int = 3,
             timeout: float = 60.0, backoff: float = 2.0) -> None:
    """Fetch `url` into `dest` via a temporary file, verified; retried on transient failures
    (network errors, truncated or corrupt transfers) with exponential backoff."""
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(dest.name + ".download")
    error = None
    for attempt in range(retries + 1):
        if attempt:
            time.sleep(backoff ** (attempt - 1))
        try:
            with urllib.request.urlopen(url, timeout=timeout) as r, open(tmp, "wb") as f:
                shutil.copyfileobj(r, f, 1 << 20)
            verify(tmp, sha256, name=dest.name)
            os.replace(tmp, dest)
            return
        except urllib.error.HTTPError as e:
            tmp.unlink(missing_ok=True)
            if e.code in (401, 403, 404, 410):  # permanent: retrying will not help
                raise DownloadError(f"{dest.name}: {url} answered HTTP {e.code} ({e.reason}). "
                                    f"Check merl.url. {OFFLINE_HINT}") from e
            error = e
        except (urllib.error.URLError, socket.timeout, ConnectionError, OSError,
                http.client.HTTPException) as e:  # e.g. IncompleteRead of a chunked body
            tmp.unlink(missing_ok=True)
            error = e
        except (ChecksumError, merl.MerlFormatError) as e:
            error = e  # verify() already removed the bad file
        log.warning("%s: attempt %d/%d failed: %s", dest.name, attempt + 1, retries + 1, error)
    if isinstance(error, (ChecksumError, merl.MerlFormatError)):
        raise error
    raise DownloadError(f"{dest.name}: could not download {url} after {retries + 1} attempt(s): "
                        f"{error}. {OFFLINE_HINT}") from error


def check_local_dir(local_dir: str | os.PathLike | None, names: list[str]) -> None:
    """DAG-time check of merl.local_dir: set, a directory, holding every <name>.binary."""
    if not local_dir:
        raise ValueError("config merl.local_dir: required when merl.source is 'local' "
                         "(a directory of <name>.binary files)")
    d = Path(local_dir)
    if not d.is_dir():
        raise FileNotFoundError(f"config merl.local_dir: {d} is not a directory")
    missing = [f"{n}.binary" for n in names if not (d / f"{n}.binary").is_file()]
    if missing:
        more = f" and {len(missing) - 10} more" if len(missing) > 10 else ""
        raise FileNotFoundError(
            f"config merl.local_dir: {d} lacks {len(missing)} of {len(names)} files: "
            f"{', '.join(missing[:10])}{more} (or restrict the materials with merl.subset)")


def local_source(local_dir: str | os.PathLike | None, name: str) -> Path:
    """Path of <name>.binary in `local_dir`, with errors naming the config key."""
    if not local_dir:
        raise ValueError("config merl.local_dir: required when merl.source is 'local'")
    src = Path(local_dir) / f"{name}.binary"
    if not src.is_file():
        raise FileNotFoundError(f"config merl.local_dir: {src} does not exist")
    return src


def copy_local(local_dir: str | os.PathLike | None, name: str, dest: str | os.PathLike,
               sha256: str | None = None, link: bool = False) -> None:
    """Copy (or symlink) <local_dir>/<name>.binary to `dest` and verify the result."""
    src = local_source(local_dir, name)
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(dest.name + ".part")
    tmp.unlink(missing_ok=True)
    if link:
        tmp.symlink_to(src.resolve())
    else:
        shutil.copyfile(src, tmp)
    verify(tmp, sha256, name=str(src))
    os.replace(tmp, dest)
