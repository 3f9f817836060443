"""Texture synthesis on the positional feature plane f_U of a plane BTF model (Triple Plane,
NeuMIP), after Xu et al. 2024 ("A Dynamic By-example BTF Synthesis Scheme"): the BTF at u is
decode(Syn(f_U, u), wi, wo), so only the 2-D positional plane is synthesised.

Registry: method -> class with `build(plane, seed, settings, luminance)`, `state()`,
`from_state(plane, seed, state, settings)` and `__call__(u) -> (N, C)` features.
Dynamic methods are pure functions of (u, seed): their state depends on the exemplar only.
`build` and `from_state` check the settings (keys and ranges: neumat.btf.synthesis.settings)
and `from_state` that the state fits the plane; both raise ValueError.
`Synthesized(model, synth)` answers the shared `btf(u, wi, wo)` query API."""

from __future__ import annotations

import torch

from neumat.btf import query
from neumat.btf.synthesis.hextile import HexTile, luminance
from neumat.btf.synthesis.hpb import HPB
from neumat.btf.synthesis.quilting import Quilting
from neumat.btf.synthesis.settings import check as check_settings
from neumat.btf.synthesis.tiling import LinearBlend, Tiling
from neumat.io import modelfile
from neumat.io.atomic import save_torch

SYNTHS = {"tiling": Tiling, "linear": LinearBlend, "hpb": HPB, "hextile": HexTile,
          "quilting": Quilting}
LABELS = {"tiling": "plain tiling", "linear": "linear blending", "hpb": "HPB",
          "hextile": "hex-tiling", "quilting": "quilting"}


def build(model, method: str, seed: int, settings: dict | None = None):
    """Synthesis `method` on `model`'s positional plane f_U."""
    if method not in SYNTHS:
        raise ValueError(f"unknown synthesis method {method!r}; choose from {list(SYNTHS)}")
    check_settings(method, settings)  # before hex-tiling's luminance pass over the plane
    lum = luminance(model) if method == "hextile" else None
    return SYNTHS[method].build(model.f_u.detach(), seed, settings or {}, lum)


class Synthesized(torch.nn.Module):
    """A plane model whose positional fetch is replaced by a synthesis: same query API,
    model(u, wi, wo) -> (N, 3) RGB; u may be float64 and arbitrarily large."""

    def __init__(self, model, synth):
        super().__init__()
        self.model, self.synth = model, synth
        self.method = f"{model.method}+{synth.method}"

    def features_u(self, u):
        return self.synth(u)

    @torch.no_grad()
    def forward(self, u, wi, wo):
        """On the CPU through the fused C query (`neumat.btf.query`: HPB and hex-tiling run
        inside its tile loop, other methods feed their features to it), else `torch_forward`;
        the same function to float32 rounding (tests/test_btf_query.py)."""
        return query.query(self.model, u, wi, wo, features_u=self.synth)

    @torch.no_grad()
    def torch_forward(self, u, wi, wo):
        """The torch path: the fallback, and the reference the fused query is tested against."""
        return torch.relu(torch.expm1(self.model.decode(self.synth(u), wi, wo)))

    def n_params(self) -> int:
        return self.model.n_params()


def save(path, method: str, seed: int, settings: dict, synths: dict) -> None:
    """One file per (material, method): the state of each plane model's synthesis (tensors
    and plain values only), written atomically."""
    obj = {"method": method, "seed": int(seed), "settings": dict(settings),
           "planes": {name: s.state() for name, s in synths.items()}}
    save_torch(path, obj)


def load(path, plane_models: dict) -> dict:
    """{plane model name: Synthesized} from a file of `save` and the loaded plane models."""
    ck = modelfile.load(path)
    cls = SYNTHS.get(ck.get("method"))
    if cls is None:
        raise ValueError(f"{path}: unknown synthesis method {ck.get('method')!r}; "
                         f"known {list(SYNTHS)}")
    missing = set(ck["planes"]) - set(plane_models)
    if missing:
        raise ValueError(f"{path}: holds synthesis states for {sorted(missing)} but those "
                         "models were not given; pass their model files")
    try:
        check_settings(ck["method"], ck["settings"])
    except ValueError as e:
        raise ValueError(f"{path}: its stored settings: {e}") from e
    out = {}
    for name, st in ck["planes"].items():
        m = plane_models[name]
        plane = m.f_u.detach().float().contiguous()
        try:
            synth = cls.from_state(plane, ck["seed"], st, ck["settings"])
        except ValueError as e:
            raise ValueError(f"{path}: the {ck['method']} state of {name!r} does not fit the "
                             f"given {name!r} model ({getattr(m, 'method', type(m).__name__)}, "
                             f"f_U (H, W, C) = {tuple(plane.shape)}): {e}; was it synthesised "
                             "from another model file?") from e
        out[name] = Synthesized(m, synth)
    return out
