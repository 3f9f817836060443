"""Generative baselines of Table 2 (M3ashy §4.3): PCA-A, PCA-N (`pca`), VAE-A, VAE-N (`vae`)."""
