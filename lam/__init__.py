"""Genie's latent action model (LAM): a discrete action per frame transition, inferred from pixels."""
