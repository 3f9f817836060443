"""Logging for workflow scripts: everything a script says, and any exception, lands in its
Snakemake log file."""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import signal
import sys
import traceback

PR_SET_PDEATHSIG = 1  # linux/prctl.h


class InputError(Exception):
    """An error whose message names the file or key and what to do (a failed download, a
    corrupt table): a script stops with that message alone on the terminal, and keeps its
    traceback for the log file. Raised as a mixin, e.g. `class DownloadError(InputError,
    RuntimeError)`."""


@contextlib.contextmanager
def script_logging(smk):
    """Route logging (and a crash's traceback) of a `script:` to `smk.log[0]`, and hold the
    script to its rule's `threads:` (see `limit_threads`); the script dies with the Snakemake
    process that started it (see `die_with_parent`)."""
    die_with_parent()
    limit_threads(getattr(smk, "threads", None))
    path = smk.log[0] if len(smk.log) else None
    handlers = [logging.FileHandler(path, mode="w")] if path else []
    handlers.append(logging.StreamHandler(sys.stderr))
    logging.basicConfig(level=logging.INFO, handlers=handlers, force=True,
                        format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    logging.captureWarnings(True)  # library warnings in the job's log too, not only the terminal
    log = logging.getLogger(f"neumat.{getattr(smk, 'rule', 'script')}")
    # how the job's threads share the cores (workflow/rules/common.smk sets the wait policy)
    log.info("threads %s, OMP_WAIT_POLICY=%s, GOMP_SPINCOUNT=%s", getattr(smk, "threads", None),
             os.environ.get("OMP_WAIT_POLICY", "unset"), os.environ.get("GOMP_SPINCOUNT", "unset"))
    try:
        yield log
    except InputError as e:
        # the terminal gets the message once, not two tracebacks per failed job, which buried
        # the remedy (an offline run of the default config; issue #20's note)
        logging.getLogger("neumat").error("failed: %s: %s", type(e).__name__, e)
        if path:
            with open(path, "a") as f:
                f.write(traceback.format_exc())
        raise SystemExit(1) from None
    except BaseException:
        logging.getLogger("neumat").error("failed:\n%s", traceback.format_exc())
        raise
    finally:
        logging.captureWarnings(False)


def die_with_parent(sig: int = signal.SIGTERM) -> bool:
    """Ask the kernel to send `sig` when our parent (the Snakemake process running this job)
    exits, even by SIGKILL: otherwise a killed run leaves its jobs running as orphans that
    keep writing outputs and holding CPUs. Linux only (prctl PR_SET_PDEATHSIG); returns
    whether it is armed."""
    if not sys.platform.startswith("linux"):
        return False
    parent = os.getppid()
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:
        return False
    if parent == 1 or os.getppid() != parent:  # the parent died before we asked
        os.kill(os.getpid(), sig)
    return True


def limit_threads(threads) -> None:
    """Torch and OpenMP to `threads` threads. By default torch starts one per core, and two
    jobs' spinning thread pools on the same 2 cores cost up to 5x CPU time (fit_eval: 215 vs
    41 CPU-s measured)."""
    if not threads:
        return
    os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = str(int(threads))
    if "torch" in sys.modules:  # already imported: the variables above come too late
        sys.modules["torch"].set_num_threads(int(threads))
