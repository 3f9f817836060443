"""One registry for every BTF representation: build, fit/train, save, load.

Every model answers `model(u, wi, wo) -> (N, 3)` RGB for batches of texture coordinates
u (N, 2; wrapping = repetitive tiling), light directions wi and view directions wo (N, 3,
unit vectors, z = surface normal)."""

from __future__ import annotations

import torch

from neumat.btf.classical import PCA, SH, Tucker
from neumat.btf.neural import NeuMIP, TriplePlane
from neumat.io import modelfile
from neumat.io.atomic import save_torch

NEURAL = {"triple_plane": TriplePlane, "neumip": NeuMIP}
GRID = {"pca": PCA, "sh": SH, "td": Tucker}
METHODS = list(NEURAL) + list(GRID)
LABELS = {"reference": "reference", "triple_plane": "Triple Plane", "neumip": "NeuMIP",
          "pca": "PCA", "sh": "SH", "td": "TD"}


def save(model, path) -> None:
    """Model file: method, constructor arguments, state dict (written atomically)."""
    if model.method in NEURAL:
        args = dict(model.kwargs)
    else:
        args = dict(width=model.width, height=model.height, light_dirs=model.light_dirs,
                    view_dirs=model.view_dirs, **model.kwargs)
    save_torch(path, {"method": model.method, "args": args, "state": model.state_dict()})


def load(path):
    ck = modelfile.require(modelfile.load(path, finite=True), ("method", "args", "state"), path,
                           "a BTF model (rule btf_<method>, e.g. btf_triple_plane)")
    cls = {**NEURAL, **GRID}.get(ck["method"])
    if cls is None:
        raise ValueError(f"{path}: unknown BTF model method {ck['method']!r}; known {METHODS}")
    # built on the meta device and handed the file's tensors (assign): no second, zero-filled
    # copy of a model that can be gigabytes (an SH model of a whole 400 x 400 BTF: 2.4 GB)
    rule = f"btf_{ck['method']}"

    def on_meta():
        with torch.device("meta"):
            return cls(**ck["args"])

    model = modelfile.build(on_meta, ck["state"], path, rule, assign=True)
    if any(t.is_meta for t in (*model.parameters(), *model.buffers())):
        # a tensor the state does not hold: build it for real
        model = modelfile.build(lambda: cls(**ck["args"]), ck["state"], path, rule)
    return model.eval()


def n_params(model) -> int:
    return model.n_params()
