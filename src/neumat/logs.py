"""Logging for workflow scripts: everything a script says, and any exception, lands in its
Snakemake log file."""

from __future__ import annotations

import contextlib
import logging
import sys
import traceback


@contextlib.contextmanager
def script_logging(smk):
    """Route logging (and a crash's traceback) of a `script:` to `smk.log[0]`."""
    path = smk.log[0] if len(smk.log) else None
    handlers = [logging.FileHandler(path, mode="w")] if path else []
    handlers.append(logging.StreamHandler(sys.stderr))
    logging.basicConfig(level=logging.INFO, handlers=handlers, force=True,
                        format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    try:
        yield logging.getLogger(f"neumat.{getattr(smk, 'rule', 'script')}")
    except BaseException:
        logging.getLogger("neumat").error("failed:\n%s", traceback.format_exc())
        raise
