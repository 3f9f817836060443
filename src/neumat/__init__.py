"""neumat: measured-material synthesis (M3ashy neural-BRDF hyperdiffusion, Triple-Plane BTF synthesis)."""

__version__ = "0.1.0"
