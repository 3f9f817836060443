"""UBO2014 BTF database: catalogue, download / local copy, and verification.

No checksums are published, so the first good copy of each file records its sha256 in a lock
file (TSV name, sha256, bytes); every later download or local copy must match it. Size and
header are always checked (a DFMF file whose matrices match its declared extents)."""

from __future__ import annotations

import fcntl
import hashlib
import http.client
import logging
import os
import shutil
import urllib.request
from pathlib import Path

import pandas as pd

from neumat.data.catalog import read_tsv
from neumat.io import dfmf
from neumat.logs import InputError

log = logging.getLogger(__name__)
CATEGORIES = ("carpet", "fabric", "felt", "leather", "stone", "wallpaper", "wood")


def load_catalog(path, names=()) -> pd.DataFrame:
    cat = read_tsv(path, "ubo2014.catalog", ["name", "category", "file"])
    unknown = sorted(set(names) - set(cat["name"]))
    if unknown:
        raise ValueError(f"config ubo2014.materials: unknown material(s) {unknown} (not in {path})")
    return cat[cat["name"].isin(names)].reset_index(drop=True) if names else cat


def sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


def check_header(path, width=400, height=400, n_dirs=151) -> dfmf.DFMF:
    """Open as DFMF (size / truncation checked by the reader), check the UBO2014 extents and
    that the factors are finite: before the sha256 of a first copy goes into the lock file,
    which would otherwise pin a damaged file as the good one."""
    b = dfmf.DFMF(path)
    got = (b.header.width, b.header.height, b.n_lights, b.n_views)
    if got != (width, height, n_dirs, n_dirs):
        raise dfmf.DFMFError(f"{path}: {got[0]} x {got[1]} texels, {got[2]} lights, {got[3]} "
                             f"views; UBO2014 files have {width} x {height}, {n_dirs}, {n_dirs}")
    b.check_finite()  # DFMFError naming the file and the factor holding NaN or inf
    return b


def verify_or_record(path, name: str, lock_file) -> str:
    """Compare the file's sha256 with the lock file's entry for `name`, or record it."""
    digest, size = sha256(path), os.path.getsize(path)
    lock_file = Path(lock_file)
    lock_file.parent.mkdir(parents=True, exist_ok=True)
    with open(lock_file, "a+") as f:
        fcntl.flock(f, fcntl.LOCK_EX)                 # parallel download jobs share the file
        f.seek(0)
        rows = [l.rstrip("\n").split("\t") for l in f if l.strip() and not l.startswith("name\t")]
        known = {r[0]: r[1] for r in rows if len(r) >= 2}
        if name in known:
            if known[name] != digest:
                raise ValueError(f"{path}: sha256 {digest} differs from {known[name]} recorded for "
                                 f"{name} in {lock_file} (corrupt download or changed upstream "
                                 f"file; delete that line to accept the new file)")
            return digest
        if f.tell() == 0:
            f.write("name\tsha256\tbytes\n")
        f.write(f"{name}\t{digest}\t{size}\n")
        log.info("recorded sha256 of %s in %s", name, lock_file)
    return digest


def check_local_dir(local_dir, files: list[str]) -> None:
    """DAG-time check of ubo2014.local_dir (source local): set, and holding every file."""
    if not local_dir:
        raise ValueError("config ubo2014.local_dir must name the directory of the .btf files "
                         "when ubo2014.source is local")
    d = Path(local_dir)
    missing = [str(d / f) for f in files if not (d / f).is_file()]
    if missing:
        raise FileNotFoundError(
            f"config ubo2014.local_dir: {len(missing)} of {len(files)} BTF files not found: "
            f"{', '.join(missing)} (copy them there, or change ubo2014.materials)")


OFFLINE_HINT = ("Offline or the server is gone? Set `ubo2014.source: local` with "
                "`ubo2014.local_dir` pointing at a directory of the .btf files, or run the offline "
                "synthetic config: --configfile config/tiny.yaml")


class FetchError(InputError, RuntimeError):
    """A BTF that could not be downloaded."""


def fetch(name: str, out, *, url: str | None = None, local_dir=None, link=False,
          lock_file, retries: int = 3, expect=(400, 400, 151)) -> None:
    """Download (url) or copy (local_dir) one material to `out`, verified; the output only
    appears once the file passed every check (a bad file is kept as <out>.rejected)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(f"{out}.part")
    if local_dir is not None:
        src = Path(local_dir) / out.name
        if not src.is_file():
            raise FileNotFoundError(f"config ubo2014.local_dir: {src} not found")
        if link:
            tmp.unlink(missing_ok=True)
            tmp.symlink_to(src.resolve())
        else:
            shutil.copyfile(src, tmp)
    else:
        for attempt in range(retries + 1):
            try:
                log.info("downloading %s (attempt %d)", url, attempt + 1)
                with urllib.request.urlopen(url, timeout=60) as r, open(tmp, "wb") as f:
                    shutil.copyfileobj(r, f, 1 << 22)
                    # a server that closes the connection cleanly mid-body ends the read
                    # without an error: compare with the length it announced
                    size, got = r.headers.get("Content-Length"), f.tell()
                    if size is not None and size.isdigit() and got != int(size):
                        raise http.client.IncompleteRead(b"", int(size) - got)
                break
            except (OSError, http.client.HTTPException) as e:
                if attempt == retries:
                    raise FetchError(f"{name}: could not download {url} after {retries + 1} "
                                     f"attempt(s): {e}. {OFFLINE_HINT}") from e
    try:
        check_header(tmp, *expect)
        verify_or_record(tmp, name, lock_file)
    except Exception:
        os.replace(tmp, f"{out}.rejected")
        raise
    os.replace(tmp, out)
