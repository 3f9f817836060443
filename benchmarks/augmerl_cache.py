"""One AugMERL consumer job's table loading: the source tables read and converted in the job (the
path before the cache) against the memory-mapped log-table cache (rule augmerl_log_tables).

Plans AugMERL as the default config does (6 permutations, `--size` materials, `--pca-dims`,
`--bins` stored bins, `--shard-size`; test fraction 0.2, seed 0), writes the cache once (timed:
the one-time cost), builds the recipe from it, then times one augmerl_shard job's work for shard
`--shard` both ways, in this process, one after the other:

  old:   load_log_tables(every source table) -> mix_values(the shard's materials)
  cache: AugMERL(recipe, cache) (np.load mmap_mode="r") -> values(the shard's materials)

and checks that both give the same float32 values, bit for bit. Prints wall and CPU seconds
(the machine may be shared: CPU seconds are the load-independent figure), their ratios, the bytes
each way reads, the load average and the machine line. The bound: the old path's table bytes per
wall second as a fraction of a plain sequential read of the same tables in this run (16 MiB
reads, page cache as the old path found it: with --cold from the device, else likely from memory);
the cache's mix touches only its bins' pages of the rows, a byte count /proc does not give, so it
has no read bound here (its CPU seconds are the figure).

    OMP_NUM_THREADS=1 python benchmarks/augmerl_cache.py /work/data/merl_decoded [--cold]

--cold drops the source tables and the cache from the page cache (posix_fadvise DONTNEED; clean
pages only, no root needed) before each timing, as on a node that has not read them yet.
"""
import argparse
import os
import resource
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from neumat import augment, machine
from neumat.io import merl


def io_counters() -> dict[str, int]:
    """This process's rchar (bytes through read()) and read_bytes (from the block device)."""
    try:
        return {k: int(v) for k, v in (line.split(": ") for line in
                                       Path("/proc/self/io").read_text().splitlines())}
    except OSError:
        return {}


def evict(paths) -> None:
    for p in paths:
        fd = os.open(p, os.O_RDONLY)
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)


class Timer:
    def __enter__(self):
        self.io, self.ru = io_counters(), resource.getrusage(resource.RUSAGE_SELF)
        self.wall, self.cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall = time.perf_counter() - self.wall
        self.cpu = time.process_time() - self.cpu
        io, ru = io_counters(), resource.getrusage(resource.RUSAGE_SELF)
        self.rchar = io.get("rchar", 0) - self.io.get("rchar", 0)
        self.disk = io.get("read_bytes", 0) - self.io.get("read_bytes", 0)
        self.majflt = ru.ru_majflt - self.ru.ru_majflt


def mix_values_before(logs, row_src, row_perm, coef, cols, chunk: int = 1 << 15):
    """augment.mix_values as it was before the cache (all sources gathered at the columns,
    then the used rows picked), for the old path's timing."""
    used = np.flatnonzero(np.abs(coef).sum(0) > 0)
    coef = coef[:, used].astype(np.float32)
    src, perm = row_src[used], row_perm[used]
    out = np.empty((len(coef), 3, len(cols)), dtype=np.float32)
    for c in range(3):
        ch = np.array(["rgb".index(augment.PERMS[p][c]) for p in perm])
        for s in range(0, len(cols), chunk):
            rows_c = logs[:, :, cols[s:s + chunk]][src, ch]
            out[:, c, s:s + chunk] = np.maximum(np.expm1(coef @ rows_c), 0.0)
    return out


def plan(names, args):
    cat = pd.DataFrame({"name": names, "type": "", "description": names, "colours": ""})
    split = augment.split_sources(names, 0.2, 0)
    rows = augment.plan_rows(cat, True, split)
    pairs = augment.plan_pairs(rows, max(args.size - len(rows), 0), 0)
    return rows, pairs, augment.build_manifest(rows, pairs, args.shard_size)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("tables", help="directory of MERL .binary tables (the sources)")
    ap.add_argument("--limit", type=int, default=0, help="first N tables only (0: all)")
    ap.add_argument("--size", type=int, default=2400)
    ap.add_argument("--pca-dims", type=int, default=300)
    ap.add_argument("--bins", type=int, default=262144, help="stored bins (config augmerl.bins)")
    ap.add_argument("--shard-size", type=int, default=200)
    ap.add_argument("--shard", default="", help="shard to time (default: the last, "
                    "interpolations only, each a mixture of every row of its split)")
    ap.add_argument("--cold", action="store_true", help="evict files from the page cache first")
    ap.add_argument("--work", default=None, help="directory for the cache (default: a temp dir)")
    args = ap.parse_args()

    paths = sorted(Path(args.tables).glob("*.binary"))[:args.limit or None]
    if len(paths) < 2:
        raise SystemExit(f"{args.tables}: {len(paths)} .binary files, need at least 2")
    names = [p.stem for p in paths]
    print(f"machine: {machine.describe()}", flush=True)
    print(f"load average at start: {os.getloadavg()[0]:.2f} (1 min)", flush=True)
    work = Path(args.work or tempfile.mkdtemp(prefix="augmerl_cache_"))
    work.mkdir(parents=True, exist_ok=True)
    npy, idx = work / "log_tables.npy", work / "log_tables_index.npz"

    rows, pairs, man = plan(names, args)
    with Timer() as t_write:
        m, v = augment.write_log_tables(paths, names, npy, idx)
    print(f"cache (once per run): {m} sources x 3 x {v} bins, {npy.stat().st_size / 1e9:.3f} GB; "
          f"written in {t_write.wall:.1f} s wall, {t_write.cpu:.1f} s CPU", flush=True)
    logs, valid, _, _ = augment.open_log_tables(npy, idx)
    recipe = augment.build_recipe(man, rows, pairs, logs, names, args.pca_dims)
    recipe.pop("pca_stats")
    bins = augment.choose_bins(valid, args.bins, 0)
    np.savez(work / "recipe.npz", bins=bins, valid_bins=valid, **recipe)
    del logs

    shard = args.shard or man["shard"].iloc[-1]
    ids = man.loc[man["shard"] == shard, "id"].to_numpy()
    coef = recipe["coef"][ids]
    used = np.abs(coef).sum(0) > 0
    pairs_used = {(s, c) for s, pm in zip(recipe["row_src"][used], recipe["row_perm"][used])
                  for c in range(3)}
    print(f"shard {shard}: {len(ids)} materials x {len(bins)} bins, mixing {used.sum()} of "
          f"{len(used)} rows ({len({s for s, _ in pairs_used})} of {m} sources)", flush=True)
    table_bytes = sum(p.stat().st_size for p in paths)

    # old: every job read and converted the source tables, then mixed in memory
    if args.cold:
        evict(paths)
    with Timer() as t_old_load:  # AugMERL.__init__ before the cache
        r = np.load(work / "recipe.npz")
        rec = {k: r[k] for k in ("coef", "row_src", "row_perm", "source_names", "bins")}
        logs, valid_old = augment.load_log_tables(paths)
    pos = np.full(merl.N_BINS, -1)
    pos[valid_old] = np.arange(len(valid_old))
    with Timer() as t_old_mix:
        old = mix_values_before(logs, rec["row_src"], rec["row_perm"], rec["coef"][ids],
                                pos[rec["bins"]])
    del logs

    # cache: map it, read what the shard uses
    if args.cold:
        evict([npy, idx])
    with Timer() as t_new_load:
        aug = augment.AugMERL(work / "recipe.npz", npy, idx)
    with Timer() as t_new_mix:
        new = aug.values(ids)
    identical = np.array_equal(old, new)

    mapped = len({s for s, _ in pairs_used}) * 3 * v * 4  # at most the used sources' rows
    # the read bound: the same tables read sequentially, in the page-cache state the old path had
    if args.cold:
        evict(paths)
    buf = bytearray(1 << 24)
    with Timer() as t_seq:
        for p in paths:
            with open(p, "rb", buffering=0) as f:
                while f.readinto(buf):
                    pass
    seq = table_bytes / t_seq.wall
    load = os.getloadavg()[0]
    print(f"{'step':<28}{'wall s':>9}{'CPU s':>9}{'read() bytes':>16}{'disk bytes':>14}"
          f"{'major faults':>14}")
    for name, t in (("old: read+convert tables", t_old_load), ("old: mix", t_old_mix),
                    ("cache: open (mmap)", t_new_load), ("cache: mix (reads pages)", t_new_mix)):
        print(f"{name:<28}{t.wall:>9.2f}{t.cpu:>9.2f}{t.rchar:>16,}{t.disk:>14,}{t.majflt:>14,}")
    old_w, old_c = t_old_load.wall + t_old_mix.wall, t_old_load.cpu + t_old_mix.cpu
    new_w, new_c = t_new_load.wall + t_new_mix.wall, t_new_load.cpu + t_new_mix.cpu
    print(f"table loading (load only): old {t_old_load.wall:.2f} s wall / {t_old_load.cpu:.2f} s "
          f"CPU, cache {t_new_load.wall:.4f} s wall -> {t_old_load.wall / t_new_load.wall:.0f}x")
    print(f"job's loading + mixing: old {old_w:.2f} s wall / {old_c:.2f} s CPU, cache "
          f"{new_w:.2f} s wall / {new_c:.2f} s CPU -> {old_w / new_w:.1f}x wall, "
          f"{old_c / new_c:.1f}x CPU")
    print(f"bytes: old reads {len(paths)} tables = {table_bytes / 1e9:.3f} GB (float64); cache "
          f"file {npy.stat().st_size / 1e9:.3f} GB, of which this shard's rows are "
          f"{mapped / 1e9:.3f} GB (float32)")
    print(f"of a sequential read of the same tables here ({seq / 1e9:.2f} GB/s, page cache "
          f"{'evicted first' if args.cold else 'warm: likely a memory rate, not the disk'}): old "
          f"read+convert {table_bytes / t_old_load.wall / seq:.1%} (its wall is "
          f"{t_old_load.wall / t_seq.wall:.1f}x the read's)")
    print(f"values identical (bit for bit): {identical}; page cache: "
          f"{'evicted before each way (--cold)' if args.cold else 'as found (warm)'}; "
          f"load average at end: {load:.2f} (1 min); machine: {machine.describe()}")
    if not identical:
        raise SystemExit("the cache changed the shard's values")
    if not args.work:
        for f in (npy, idx, work / "recipe.npz"):
            f.unlink()
        work.rmdir()


if __name__ == "__main__":
    main()
