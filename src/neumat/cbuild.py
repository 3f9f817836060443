"""Build and cache the package's C kernels (`fit_step.c`, `btf/query_kernel.c`,
`metrics/l1_kernel.c`) for a target.

Each shared library is built with the system C compiler (`$CC`, default `cc`) for a `-march`
(`native` by default; a named level such as `x86-64-v3` builds an AVX2 variant on any x86
host, for tests and benchmarks) into `$NEUMAT_CACHE` (default `~/.cache/neumat`), keyed by a hash
of the source, the compiler, the flags and (for `native`) the CPU, so a cluster with mixed nodes
builds one per CPU type. The kernels pick their vector width and register blocking from the
target ISA at compile time.
"""

from __future__ import annotations

import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path

log = logging.getLogger(__name__)
X86 = platform.machine().lower() in ("x86_64", "amd64")
# x86-64 micro-architecture levels and a CPU flag each needs (the rest come with it)
X86_LEVELS = {"x86-64": "sse2", "x86-64-v2": "sse4_2", "x86-64-v3": "avx2",
              "x86-64-v4": "avx512f"}


def cpu_id() -> str:
    """What -march=native depends on: the CPU model and its feature flags."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        return "\n".join(sorted({l for l in lines if l.startswith(("model name", "flags"))}))
    except OSError:
        return platform.processor() + platform.machine()


def flags(march: str, fast_math: bool = True, tune: str | None = None) -> list[str]:
    """Compile flags; fast_math=False keeps IEEE arithmetic (a kernel that must equal torch);
    `tune` overrides the tuning that -march implies (-mtune)."""
    f = ["-O3", *(["-ffast-math"] if fast_math else []), f"-march={march}", "-fPIC"]
    if tune:
        f.append(f"-mtune={tune}")
    if X86:
        f.append("-mprefer-vector-width=512")  # use zmm registers where -march has them
    return f


def runs_here(march: str) -> bool:
    """Whether code built for `march` can run on this CPU (known x86 levels are checked; any
    other -march is taken on trust, native always runs)."""
    need = X86_LEVELS.get(march)
    if need is None:
        return True
    return X86 and need in cpu_id().split()


def library_path(source: Path, march: str, fast_math: bool = True,
                 tune: str | None = None) -> Path | None:
    """Where the library of `source` for `march` is or will be cached; None without a compiler."""
    cc = os.environ.get("CC", "cc")
    if shutil.which(cc) is None:
        return None
    version = subprocess.run([cc, "--version"], capture_output=True, text=True).stdout
    key = hashlib.sha256("\0".join([source.read_text(), version, " ".join(flags(march, fast_math, tune)),
                                    cpu_id() if march == "native" else ""]).encode())
    cache_dir = Path(os.environ.get("NEUMAT_CACHE", Path.home() / ".cache" / "neumat"))
    tag = "" if march == "native" else f"{march}-"
    return cache_dir / f"{source.stem}-{tag}{key.hexdigest()[:16]}.so"


def _compile(cc: str, source: Path, march: str, out: Path, fast_math: bool = True,
             tune: str | None = None) -> None:
    """Compile to a temporary name and rename: concurrent jobs never load a half-written file.

    -ffast-math only when compiling: linking a shared library with it would add crtfastmath,
    which sets flush-to-zero for the whole process (torch included) when loaded."""
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
        obj, lib = Path(tmp) / f"{source.stem}.o", Path(tmp) / out.name
        for cmd in ([cc, *flags(march, fast_math, tune), "-c", str(source), "-o", str(obj)],
                    [cc, "-shared", str(obj), "-o", str(lib), "-lm"]):
            r = subprocess.run(cmd, capture_output=True, text=True)
            if r.returncode:
                raise RuntimeError(f"compiling {source.name} failed: {' '.join(cmd)}\n{r.stderr}")
        os.replace(lib, out)


def build(source: Path, march: str, fallback: str, fast_math: bool = True,
          tune: str | None = None) -> Path | None:
    """The built library of `source` for `march`, or None with the reason logged (no compiler,
    a target this CPU cannot run, a failed build); `fallback` says what runs instead."""
    path = library_path(source, march, fast_math, tune)
    if path is None:
        log.warning("no C compiler (%s): %s", os.environ.get("CC", "cc"), fallback)
        return None
    if not runs_here(march):
        log.warning("%s built for -march=%s cannot run on this CPU: %s", source.name, march,
                    fallback)
        return None
    if not path.exists():
        log.info("compiling %s -march=%s -> %s", source.name, march, path)
        try:
            _compile(os.environ.get("CC", "cc"), source, march, path, fast_math, tune)
        except (RuntimeError, OSError) as e:
            log.warning("%s; %s", e, fallback)
            return None
    return path
