"""Share of negative values among the above-horizon bins of MERL tables.

AugMERL drops a bin from every material when any source is negative there, so a table with many
negative bins (a sign-flipped block, a bad conversion) silently shrinks everyone's data. This
measures the share on real tables, to set `neumat.io.merl.MAX_NEGATIVE_SHARE` (the error
threshold) well above it:

    python benchmarks/merl_negative_bins.py resources/merl/*.binary

With the published NBRDF fits of the 100 MERL materials (decoded with nbrdf_to_merl.py; the real
files store -1 below the horizon only) every table has the same share: the bins whose centre is
above the horizon but whose lower edge, where MERL's grid is evaluated, is not."""
import argparse

import numpy as np

from neumat import machine
from neumat.io import merl


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("tables", nargs="+", help="MERL .binary files")
    args = ap.parse_args()
    print(f"machine: {machine.describe()}", flush=True)
    shares = []
    for path in args.tables:
        count, n = merl.negative_bins(merl.read_merl(path))
        shares.append(count / n)
        print(f"{path}\t{count}\t{n}\t{count / n:.4%}")
    s = np.array(shares)
    print(f"{len(s)} tables: negative share of above-horizon bins min {s.min():.4%}, "
          f"median {np.median(s):.4%}, max {s.max():.4%}; "
          f"error threshold (merl.MAX_NEGATIVE_SHARE) {merl.MAX_NEGATIVE_SHARE:.1%}")


if __name__ == "__main__":
    main()
