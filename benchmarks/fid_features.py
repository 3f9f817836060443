"""Inception-v3 FID features (neumat.metrics.fid.features) with the network as fid_network gives
it (inception.for_inference: BatchNorm folded into the convolutions, channels-last weights)
against the plain port (neumat.metrics.inception.load_packaged_inception), in the same run:
interleaved rounds, the best of each. Prints wall and CPU time per image, the ratio, the
convolutions' FLOP rate against this machine's fp32 matmul rate (machine.sgemm_peak, same
threads), and the largest feature difference between the two.

    OMP_NUM_THREADS=2 python benchmarks/fid_features.py [--images 32] [--resolution 128] [--repeat 5]
"""
import argparse
import time

import numpy as np
import torch

from neumat import machine
from neumat.metrics import fid, inception


def conv_flop(model) -> float:
    """FLOP of the convolutions for one image (2 per multiply-add), from one forward pass."""
    total = []

    def hook(m, inp, out):
        k = m.in_channels // m.groups * m.kernel_size[0] * m.kernel_size[1]
        total.append(2 * out.numel() * k)

    hs = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, torch.nn.Conv2d)]
    with torch.no_grad():
        model.forward_dims(torch.rand(1, 3, 64, 64))
    for h in hs:
        h.remove()
    return float(sum(total))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--images", type=int, default=32, help="images per timed call (default 32)")
    ap.add_argument("--resolution", type=int, default=128, help="input size before the resize to 299 (default 128)")
    ap.add_argument("--repeat", type=int, default=5, help="interleaved rounds, best kept (default 5)")
    a = ap.parse_args()
    threads = torch.get_num_threads()
    print(f"machine: {machine.describe()}; torch {torch.__version__}, ISA "
          f"{torch.backends.cpu.get_cpu_capability()}, {threads} threads")
    plain = inception.load_packaged_inception()
    fast, reason = inception.fid_network(None)
    if fast is None:
        raise SystemExit(f"FID network unavailable: {reason}")
    imgs = np.random.default_rng(0).random((a.images, a.resolution, a.resolution, 3), np.float32)
    runs = {"plain port": plain, "for_inference": fast}
    wall, cpu, feats = {k: np.inf for k in runs}, {k: np.inf for k in runs}, {}
    with torch.no_grad():
        for m in runs.values():
            fid.features(m, imgs[:4])  # warm-up: oneDNN primitives, first touch
        for _ in range(a.repeat):
            for k, m in runs.items():
                t, c = time.perf_counter(), time.process_time()
                feats[k] = fid.features(m, imgs)
                wall[k] = min(wall[k], time.perf_counter() - t)
                cpu[k] = min(cpu[k], time.process_time() - c)
    flop = conv_flop(plain) * a.images
    peak_wall, _ = machine.sgemm_peak(threads)
    print(f"{a.images} images {a.resolution} px -> 299 px, {flop / a.images / 1e9:.2f} GFLOP of "
          f"convolutions each; fp32 matmul rate {peak_wall / 1e9:.0f} GFLOP/s on {threads} threads")
    print(f"{'':16s} {'ms/image':>9s} {'CPU-ms/image':>13s} {'GFLOP/s':>8s} {'of matmul':>10s}")
    for k in runs:
        rate = flop / wall[k]
        print(f"{k:16s} {wall[k] / a.images * 1e3:9.1f} {cpu[k] / a.images * 1e3:13.1f} "
              f"{rate / 1e9:8.1f} {rate / peak_wall:10.1%}")
    print(f"for_inference / plain: wall {wall['for_inference'] / wall['plain port']:.3f}, CPU "
          f"{cpu['for_inference'] / cpu['plain port']:.3f}")
    for d in (2048, 64):
        ref = feats["plain port"][d]
        diff = np.abs(feats["for_inference"][d] - ref).max()
        print(f"{d}-d features: largest difference {diff:.2e} (largest value {np.abs(ref).max():.2f})")


if __name__ == "__main__":
    main()
