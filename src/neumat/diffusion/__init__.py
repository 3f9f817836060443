"""Hyperdiffusion over NBRDF weight vectors (M3ashy §3.3): transformer denoiser (`model`),
DDPM schedules + DDIM sampler with classifier-free guidance (`schedule`), training with EMA
and exact resume, sampling (`train`), and physical plausibility checks (`plausibility`)."""

from neumat.diffusion.model import Denoiser, DenoiserConfig, Normalizer
from neumat.diffusion.schedule import Diffusion, ScheduleConfig, guided
from neumat.diffusion.train import Sampler, TrainConfig, train

__all__ = ["Denoiser", "DenoiserConfig", "Normalizer", "Diffusion", "ScheduleConfig", "guided",
           "Sampler", "TrainConfig", "train"]
