"""Condition encoders for the hyperdiffusion model (M3ashy §3.3, §4.4): a pretrained sentence
encoder for text (`text`) and a small ResNet trained here for reference images (`image`)."""
