"""Mitsuba 3 BSDF plugin `neumat_brdf`: a neural field (NBRDF weight vector) or a MERL table
evaluated inside Mitsuba, with importance sampling fitted to the material.

Evaluation: wi, wo (local frame) -> Rusinkiewicz (theta_h, theta_d, phi_d) in Dr.Jit; a neural
field runs its 6 -> 21 -> 21 -> 3 MLP, a MERL table is read at its nearest bin
(`neumat.io.merl` binning) with one gather per channel.

A material's numbers (its weights, its lobe) enter the traced kernel as opaque inputs for small
renders: the kernel is then the same for every material of a scene layout, and Dr.Jit compiles
it once and caches it in ~/.drjit. As literals, every new material - every sample - is a new
LLVM compile, 0.25 s at 48 px and 4 spp where the render takes 0.01 s; but a large render runs
faster with literals (`INLINE_SAMPLES`; `benchmarks/mitsuba_materials.py` measures both).

Sampling: a mixture of a cosine lobe and a GGX lobe (half-vector sampling of D(h) cos theta_h,
reflected about h). The lobe is fitted once per material from the BRDF along theta_d = 0:
the diffuse level kd is the value at theta_h = 80 deg, the GGX roughness alpha comes from the
theta_h where the specular excess halves (D(theta)/D(0) = 1/2 at tan^2 theta = alpha^2 (sqrt2-1)),
and the specular probability is the estimated specular albedo 4 pi alpha^2 (f(0) - kd) over the
total, clipped to [0.05, 0.95]; alpha is clipped to [0.005, 0.6] (rougher GGX lobes send
much of their mass below the horizon, and the cosine lobe covers such materials). MIS with emitter sampling is done by Mitsuba's path tracer.

Scene XML: `<bsdf type="neumat_brdf"><string name="filename" value="x.binary|w.npy"/>
<integer name="index" value="0"/></bsdf>` loads a MERL table or one row of a weights file
(relative to the scene's folder); `select_variant()` registers the plugin before `load_file`.
`<boolean name="inline" value="true"/>` bakes the material into the kernel (default false;
`neumat render` sets it for large renders).

Variant: `select_variant()`, the one place Mitsuba is first imported, picks `llvm_ad_rgb` when a
libLLVM >= 16 is found (Dr.Jit's LLVM backend crashes with 14/15): the system's, else the PyPI
wheel karellen-llvm-core installed with neumat. Without one it falls back to `scalar_rgb` with a
warning (slow: the Python BSDF is then called per ray, so keep resolution x spp small).
"""

from __future__ import annotations

import glob
import logging
import os
import sys
from dataclasses import dataclass

import numpy as np
import torch

from neumat import nbrdf
from neumat.io import merl

log = logging.getLogger(__name__)
PLUGIN = "neumat_brdf"
_LLVM_NEWEST = 30  # search libLLVM versions from here down (karellen-llvm-core: 23)
_LLVM_GLOBS = ["/usr/lib/x86_64-linux-gnu/libLLVM-{v}.so*", "/usr/lib/llvm-{v}/lib/libLLVM*.so*",
               "/usr/lib64/libLLVM-{v}.so*", "/usr/local/lib/libLLVM-{v}.so*",
               "/opt/homebrew/opt/llvm@{v}/lib/libLLVM*.dylib"]


# ----------------------------------------------------------------------------- variant


def find_libllvm(min_version: int = 16) -> str | None:
    """Path of a usable libLLVM (>= min_version), made loadable: DRJIT_LIBLLVM_PATH if set,
    else the newest system library, else one in this environment's prefix: conda-forge
    `libllvm19`, or PyPI `karellen-llvm-core` (a dependency, so `pip install -e .` alone
    gives Mitsuba its fast variant; a system libLLVM still wins)."""
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env and os.path.exists(env):
        lib = _with_runtime(env)
        if llvm_version(lib) is not None:  # >= 16 (below it has no LLVMGetVersion)
            return lib
        log.warning("DRJIT_LIBLLVM_PATH=%s is not a libLLVM >= %d (Dr.Jit's kernels crash on "
                    "LLVM 14 and 15): looking for another", env, min_version)
    prefixes = [p for p in (os.environ.get("CONDA_PREFIX"), sys.prefix) if p]
    local = [f"{p}/lib/libLLVM-{{v}}.so*" for p in prefixes] + [f"{p}/lib/libLLVM.so.{{v}}*" for p in prefixes]
    for patterns in (_LLVM_GLOBS, local):
        for v in range(_LLVM_NEWEST, min_version - 1, -1):
            for pattern in patterns:
                hits = sorted(glob.glob(pattern.format(v=v)))
                if hits:
                    return _with_runtime(hits[0])
    return None


def llvm_version(lib: str) -> tuple[int, int, int] | None:
    """(major, minor, patch) of the libLLVM at `lib` by its LLVMGetVersion, which LLVM has
    from 16 on; None for an older LLVM or a library that is not one (loaded RTLD_LOCAL, as
    `_with_runtime`)."""
    import ctypes

    try:
        get = ctypes.CDLL(lib, mode=ctypes.RTLD_LOCAL).LLVMGetVersion
    except (OSError, AttributeError):
        return None
    v = [ctypes.c_uint() for _ in range(3)]
    get(*(ctypes.byref(x) for x in v))
    return tuple(x.value for x in v)


def _with_runtime(lib: str) -> str:
    """Load the LLVM C++ runtime that karellen-llvm-core ships beside its libLLVM
    (<prefix>/lib/<triple>/lib{unwind,c++abi,c++}.so.1.0): libLLVM needs libc++.so.1, and pip
    does not always create the .so.1 names it links against; once loaded, the loader finds
    them by soname. RTLD_LOCAL, never GLOBAL: a global libc++abi takes over C++ exceptions of
    every later extension (matplotlib's pybind11 modules then abort on import)."""
    import ctypes

    real = os.path.realpath(lib)
    for name in ("libunwind", "libc++abi", "libc++"):
        hits = sorted(glob.glob(f"{os.path.dirname(real)}/*-linux-gnu/{name}.so.1*"))
        if hits:
            ctypes.CDLL(hits[-1], mode=ctypes.RTLD_LOCAL)  # .so.1.0 sorts last: the file itself
    return real


# Dr.Jit reads DRJIT_LIBLLVM_PATH once, when it is imported, and with an LLVM it did not see then
# its kernels fail to compile ("LLVM ERROR: Cannot select: fminimum"). So the library is found
# here, when this module is imported (neumat.render.scenes imports it), before Mitsuba is.
_DRJIT_FIRST = "drjit" in sys.modules and not os.environ.get("DRJIT_LIBLLVM_PATH")
_LIBLLVM = None if _DRJIT_FIRST else find_libllvm()
if _LIBLLVM:
    os.environ["DRJIT_LIBLLVM_PATH"] = _LIBLLVM
elif not _DRJIT_FIRST:  # an older LLVM named there would crash Dr.Jit's kernels: none at all
    os.environ.pop("DRJIT_LIBLLVM_PATH", None)


def select_variant(preference: str = "auto") -> str:
    """Set and return the Mitsuba variant (see module docstring). Call before building scenes."""
    if preference not in ("auto", "llvm_ad_rgb", "scalar_rgb"):
        raise ValueError(f"render.mitsuba.variant must be auto, llvm_ad_rgb or scalar_rgb, "
                         f"got {preference!r}")
    variant = preference
    if preference != "scalar_rgb":
        why = ("Dr.Jit was imported before neumat.render (import it first, or set "
               "DRJIT_LIBLLVM_PATH)" if _DRJIT_FIRST else
               "no libLLVM >= 16 found (pip install karellen-llvm-core, apt-get install "
               "libllvm19, or set DRJIT_LIBLLVM_PATH)")
        if _LIBLLVM:
            variant = "llvm_ad_rgb"
        elif preference == "llvm_ad_rgb":
            raise RuntimeError(f"render.mitsuba.variant = llvm_ad_rgb: {why}")
        else:
            log.warning("%s: falling back to the slow scalar_rgb variant", why)
            variant = "scalar_rgb"
    import mitsuba as mi

    try:
        mi.set_variant(variant)
    except Exception as e:  # e.g. Dr.Jit's LLVM backend would not start with this library
        if variant == "scalar_rgb" or preference == "llvm_ad_rgb":
            raise RuntimeError(f"render.mitsuba.variant = {preference}: Mitsuba's {variant} "
                               f"does not start ({type(e).__name__}: {e})") from e
        log.warning("Mitsuba's llvm_ad_rgb does not start with %s (%s: %s): falling back to the "
                    "slow scalar_rgb variant", _LIBLLVM, type(e).__name__, e)
        variant = "scalar_rgb"
        mi.set_variant(variant)
    register()
    return variant


# ----------------------------------------------------------------------------- materials


@dataclass
class Material:
    """A BRDF for the plugin: `weights` (675,) of a neural field, or `table` (3, 90, 90, 180)."""
    name: str
    weights: np.ndarray | None = None
    table: np.ndarray | None = None
    activation: str = "relu"

    def __post_init__(self):
        if (self.weights is None) == (self.table is None):
            raise ValueError(f"material {self.name!r}: give exactly one of weights or table")
        if self.weights is not None and np.shape(self.weights) != (nbrdf.N_PARAMS,):
            raise ValueError(f"material {self.name!r}: weights must have shape (675,), "
                             f"got {np.shape(self.weights)}")
        if self.table is not None and np.shape(self.table) != merl.SHAPE:
            raise ValueError(f"material {self.name!r}: table must have shape {merl.SHAPE}")

    def evaluate(self, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        """Reference evaluation with numpy / torch: (N, 3) directions -> (N, 3) BRDF."""
        if self.table is not None:
            return merl.lookup(self.table, wi, wo)
        x = torch.as_tensor(merl.half_diff_cartesian(*merl.dirs_to_half_diff(wi, wo)),
                            dtype=torch.float32)
        with torch.no_grad():
            f = nbrdf.forward(torch.as_tensor(self.weights, dtype=torch.float32)[None], x,
                              self.activation)[0].double().numpy()
        return np.where(((wi[:, 2] > 0) & (wo[:, 2] > 0))[:, None], f, 0.0)


def fit_lobe(material: Material) -> tuple[float, float]:
    """(alpha, p_specular) of the GGX + cosine sampling mixture (see module docstring)."""
    th = np.radians(np.linspace(0, 80, 161))
    wi, wo = merl.half_diff_to_dirs(th, np.zeros_like(th), np.zeros_like(th))
    f = material.evaluate(wi, wo).mean(1)
    kd = max(f[-1], 0.0)
    spec = f - kd
    if spec[0] <= 1e-6 * max(kd, 1e-12) or spec[0] <= 0:
        return 0.5, 0.05
    below = np.flatnonzero(spec < spec[0] / 2)
    theta_half = th[below[0]] if len(below) else th[-1]
    alpha = float(np.clip(np.tan(theta_half) / np.sqrt(np.sqrt(2) - 1), 0.005, 0.6))
    spec_albedo = 4 * np.pi * alpha ** 2 * spec[0]
    p_spec = spec_albedo / (spec_albedo + np.pi * kd + 1e-12)
    return alpha, float(np.clip(p_spec, 0.05, 0.95))


_MATERIALS: dict[str, Material] = {}


# From this many camera samples (resolution^2 x spp) a render bakes the material into its kernel:
# its compile (0.23-0.24 s) then pays for itself in faster samples, 97-104 against 190-224 ns a
# sample at 256 px and 64 spp, from 2.0-2.5 M samples (`benchmarks/mitsuba_materials.py`, two
# runs, AMD EPYC AVX-512, 2 cores)
INLINE_SAMPLES = 1 << 21


def bsdf_dict(material: Material, samples: int = 0) -> dict:
    """Scene-dictionary entry of the plugin for `material` (registers it under its name), for a
    render of `samples` camera samples: at INLINE_SAMPLES or more the material's numbers are
    literals of the kernel, else its inputs (one kernel for every material)."""
    _MATERIALS[material.name] = material
    return {"type": PLUGIN, "material": material.name, "inline": samples >= INLINE_SAMPLES}


def _material_key(path, index: int) -> str:
    return f"{os.path.abspath(path)}#{index}"


def material_from_file(path, index: int = 0, activation: str = "relu") -> Material:
    """A MERL `.binary` table, or row `index` of a weights `.npy` (N, 675) / (675,), as a Material
    named by its absolute path and index (what a scene XML's `filename` entry loads)."""
    path = str(path)
    key = _material_key(path, index)
    if path.endswith(".binary"):
        return Material(key, table=merl.read_merl(path))
    if path.endswith(".npy"):
        w = np.load(path)  # allow_pickle=False
        if w.dtype.kind not in "fiu" or w.ndim == 0 or w.size == 0 or w.shape[-1] != nbrdf.N_PARAMS:
            raise ValueError(f"{path}: holds {w.dtype} of shape {w.shape}, not NBRDF weights "
                             f"(N, {nbrdf.N_PARAMS}) or ({nbrdf.N_PARAMS},)")
        w = w.reshape(-1, nbrdf.N_PARAMS)
        if not 0 <= index < len(w):
            raise ValueError(f"{path}: holds {len(w)} weight vectors, index {index} asked for")
        if not np.isfinite(w[index]).all():
            raise ValueError(f"{path}: weight vector {index} holds NaN or inf")
        return Material(key, weights=w[index].astype(np.float32), activation=activation)
    raise ValueError(f"{path}: {PLUGIN} loads MERL .binary tables or NBRDF weights .npy files")


# ----------------------------------------------------------------------------- plugin


def _rusinkiewicz(dr, mi, wi, wo):
    """Dr.Jit twin of `neumat.io.merl.dirs_to_half_diff` (+ the NBRDF 6-D input)."""
    h = dr.normalize(wi + wo)
    theta_h = dr.acos(dr.clip(h.z, -1, 1))
    phi_h = dr.atan2(h.y, h.x)
    c, s = dr.cos(phi_h), dr.sin(phi_h)
    x, y = c * wi.x + s * wi.y, -s * wi.x + c * wi.y
    ct, st = dr.cos(theta_h), dr.sin(theta_h)
    d = mi.Vector3f(ct * x - st * wi.z, y, st * x + ct * wi.z)
    return theta_h, d


def register():
    """Register `neumat_brdf` with Mitsuba (after `mi.set_variant`)."""
    import drjit as dr
    import mitsuba as mi

    flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide

    class NeumatBRDF(mi.BSDF):
        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            if "filename" in props:  # a scene XML: <string name="filename" value="x.binary|w.npy"/>
                index = int(props["index"]) if "index" in props else 0
                act = props["activation"] if "activation" in props else "relu"
                # relative to the scene file (load_file puts its folder on the resolver)
                path = str(mi.file_resolver().resolve(props["filename"]))
                name = bsdf_dict(material_from_file(path, index, act))["material"]
            else:
                name = props["material"]
            if name not in _MATERIALS:
                raise ValueError(f"{PLUGIN}: unknown material {name!r}; build the scene "
                                 "entry with neumat.render.mitsuba_bsdf.bsdf_dict")
            self.material = m = _MATERIALS[name]
            self.alpha, self.p_spec = fit_lobe(m)
            self.scalar = mi.variant().startswith("scalar")
            # the kernel's copies: literals, or opaque so that the kernel does not depend on the
            # material (bsdf_dict)
            inline = (props["inline"] if "inline" in props else False) or self.scalar
            value = float if inline else (lambda v: dr.opaque(mi.Float, float(v)))
            self.lobe = (value(self.alpha), value(self.p_spec))
            if self.scalar:
                pass  # evaluated per call by Material.evaluate
            elif m.table is not None:
                self.table = mi.Float(np.maximum(m.table, 0).astype(np.float32).ravel())
            else:
                self.params = [[[value(v) for v in row] for row in np.atleast_2d(p)]
                               for p in (q[0].numpy().astype(np.float64) for q in
                                         nbrdf.unflatten(torch.as_tensor(m.weights)[None]))]
            self.m_components = [flags]
            self.m_flags = flags

        # -- BRDF value
        def _f(self, wi, wo):
            if self.scalar:  # one pair per call: the numpy/torch reference path is faster
                f = self.material.evaluate(np.array([[wi.x, wi.y, wi.z]]),
                                           np.array([[wo.x, wo.y, wo.z]]))[0]
                return mi.Color3f(*(float(v) for v in f))
            theta_h, d = _rusinkiewicz(dr, mi, wi, wo)
            if self.material.table is not None:
                return self._table(theta_h, d)
            return self._mlp([dr.sin(theta_h), theta_h * 0, dr.cos(theta_h), d.x, d.y, d.z])

        def _table(self, theta_h, d):
            theta_d = dr.acos(dr.clip(d.z, -1, 1))
            phi_d = dr.atan2(d.y, d.x)
            phi_d = dr.select(phi_d < 0, phi_d + dr.pi, phi_d)
            ih = dr.clip(mi.Int32(dr.floor(dr.sqrt(dr.maximum(theta_h, 0) / (dr.pi / 2)) * merl.N_TH)),
                         0, merl.N_TH - 1)
            idd = dr.clip(mi.Int32(dr.floor(theta_d / (dr.pi / 2) * merl.N_TD)), 0, merl.N_TD - 1)
            ip = dr.clip(mi.Int32(dr.floor(phi_d / dr.pi * merl.N_PD)), 0, merl.N_PD - 1)
            idx = mi.UInt32(ip + merl.N_PD * (idd + merl.N_TD * ih))
            return mi.Color3f(*(dr.gather(mi.Float, self.table, idx + c * merl.N_BINS)
                                for c in range(3)))

        def _mlp(self, x):
            W1, (b1,), W2, (b2,), W3, (b3,) = self.params
            act = self.material.activation
            slope = 0.0 if act == "relu" else 0.01

            def layer(inp, W, b, last=False):
                outs = []
                for j in range(len(b)):
                    v = b[j]
                    for k in range(len(inp)):
                        v = dr.fma(inp[k], W[j][k], v)
                    outs.append(v if last else dr.maximum(v, slope * v))
                return outs

            o = layer(layer(layer(x, W1, b1), W2, b2), W3, b3, last=True)
            return mi.Color3f(*(dr.maximum(dr.exp(v) - 1, 0) for v in o))

        # -- sampling
        def _pdf(self, wi, wo):
            alpha, p_spec = self.lobe
            a2 = alpha ** 2
            h = dr.normalize(wi + wo)
            cos_h = h.z
            tan2 = dr.maximum(1 - cos_h * cos_h, 0) / dr.maximum(cos_h * cos_h, 1e-12)
            D = a2 / (dr.pi * cos_h ** 4 * (a2 + tan2) ** 2)
            spec = D * cos_h / (4 * dr.maximum(dr.dot(wo, h), 1e-8))
            diff = dr.maximum(wo.z, 0) / dr.pi
            pdf = p_spec * dr.select(cos_h > 0, spec, 0) + (1 - p_spec) * diff
            return dr.select((wi.z > 0) & (wo.z > 0), pdf, 0)

        def _value(self, si, wo, active):
            ok = active & (si.wi.z > 0) & (wo.z > 0)
            return dr.select(ok, self._f(si.wi, wo) * wo.z, 0)

        def eval(self, ctx, si, wo, active=True):
            return self._value(si, wo, active)

        def pdf(self, ctx, si, wo, active=True):
            return self._pdf(si.wi, wo)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self._value(si, wo, active), self._pdf(si.wi, wo)

        def sample(self, ctx, si, sample1, sample2, active=True):
            wi = si.wi
            alpha, p_spec = self.lobe
            # GGX half vector from D(h) cos(theta_h)
            phi = 2 * dr.pi * sample2.y
            tan2 = alpha ** 2 * sample2.x / dr.maximum(1 - sample2.x, 1e-8)
            cos_t = dr.rsqrt(1 + tan2)
            sin_t = dr.safe_sqrt(1 - cos_t * cos_t)
            h = mi.Vector3f(sin_t * dr.cos(phi), sin_t * dr.sin(phi), cos_t)
            wo_spec = 2 * dr.dot(wi, h) * h - wi
            wo_diff = mi.warp.square_to_cosine_hemisphere(sample2)
            wo = dr.select(sample1 < p_spec, wo_spec, wo_diff)
            bs = mi.BSDFSample3f()
            bs.wo = wo
            bs.pdf = self._pdf(wi, wo)
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
            bs.sampled_component = mi.UInt32(0)
            ok = active & (wi.z > 0) & (wo.z > 0) & (bs.pdf > 0)
            value = self._value(si, wo, ok) / dr.select(ok, bs.pdf, 1)
            return bs, dr.select(ok, value, 0)

        def traverse(self, callback):
            pass

        def parameters_changed(self, keys):
            pass

        def to_string(self):
            return f"NeumatBRDF[{self.material.name}, alpha={self.alpha:.3f}, p_spec={self.p_spec:.2f}]"

    mi.register_bsdf(PLUGIN, lambda props: NeumatBRDF(props))
