"""Tokenizer training losses: L1 + LPIPS + PatchGAN (hinge or non-saturating, adaptive weight, LeCAM) + LFQ terms.

The recipe of the published MAGVIT2 tokenizers (docs/formats.md §4). `VQLoss` owns the discriminator and the LeCAM
statistics; the trainer calls `generator_loss` for the autoencoder update and `discriminator_loss` for the
discriminator update of the same batch.
"""
from typing import Dict, Optional, Tuple

import torch
import torch.nn as nn
import torch.nn.functional as F

from magvit2.config import VQConfig
from magvit2.lfq import LFQOutput

GAN_LOSSES = ("hinge", "non_saturating")
GAN_WEIGHTINGS = ("adaptive", "fixed")


class NLayerDiscriminator(nn.Module):
    """PatchGAN discriminator (Isola et al.): images (B, C, H, W) -> real/fake logits per patch (B, 1, h, w).

    `num_layers` stride-2 4x4 convs (width doubling up to 8x `base_channels`), one stride-1 conv, then a 1-channel
    4x4 conv. Each logit sees a 70x70 receptive field for num_layers = 3.
    """

    def __init__(self, in_channels: int = 3, base_channels: int = 64, num_layers: int = 3):
        super().__init__()
        layers = [nn.Conv2d(in_channels, base_channels, 4, stride=2, padding=1), nn.LeakyReLU(0.2)]
        width = base_channels
        for n in range(1, num_layers + 1):
            out_width = base_channels * min(2 ** n, 8)
            stride = 2 if n < num_layers else 1
            layers += [nn.Conv2d(width, out_width, 4, stride=stride, padding=1, bias=False),
                       nn.BatchNorm2d(out_width), nn.LeakyReLU(0.2)]
            width = out_width
        layers.append(nn.Conv2d(width, 1, 4, stride=1, padding=1))
        self.main = nn.Sequential(*layers)
        self.apply(_init_weights)
        # each stride-2 conv halves the side, the two stride-1 4x4 convs take 1 pixel each
        self.min_input_size = 3 * 2 ** num_layers

    def forward(self, x_BCHW: torch.Tensor) -> torch.Tensor:
        if min(x_BCHW.shape[-2:]) < self.min_input_size:
            raise ValueError(f"the {len(self.main) // 3}-layer patch discriminator needs images of at least "
                             f"{self.min_input_size}x{self.min_input_size}, got {tuple(x_BCHW.shape[-2:])}; "
                             f"use fewer discriminator layers")
        return self.main(x_BCHW)


def _init_weights(module: nn.Module) -> None:
    """DCGAN initialization, as the PatchGAN discriminators of taming / Open-MAGVIT2 use."""
    if isinstance(module, nn.Conv2d):
        nn.init.normal_(module.weight, 0.0, 0.02)
    elif isinstance(module, nn.BatchNorm2d):
        nn.init.normal_(module.weight, 1.0, 0.02)
        nn.init.zeros_(module.bias)


def hinge_d_loss(logits_real: torch.Tensor, logits_fake: torch.Tensor) -> torch.Tensor:
    return 0.5 * (F.relu(1.0 - logits_real).mean() + F.relu(1.0 + logits_fake).mean())


def hinge_g_loss(logits_fake: torch.Tensor) -> torch.Tensor:
    return -logits_fake.mean()


def non_saturating_d_loss(logits_real: torch.Tensor, logits_fake: torch.Tensor) -> torch.Tensor:
    """-log sigmoid(real) - log(1 - sigmoid(fake)), averaged over patches."""
    return F.softplus(-logits_real).mean() + F.softplus(logits_fake).mean()


def non_saturating_g_loss(logits_fake: torch.Tensor) -> torch.Tensor:
    """-log sigmoid(fake): the generator maximizes the log-probability that its output is judged real."""
    return F.softplus(-logits_fake).mean()


def adaptive_generator_weight(rec_loss: torch.Tensor, gan_loss: torch.Tensor, last_layer: torch.Tensor,
                              disc_weight: float, max_weight: float = 1e4) -> torch.Tensor:
    """disc_weight * |d rec / d W| / |d gan / d W| at the decoder's last layer W (Esser et al., VQGAN).

    Balances the two gradients where they meet the output; detached, so it is a weight and not a loss term.
    """
    rec_grad = torch.autograd.grad(rec_loss, last_layer, retain_graph=True)[0]
    gan_grad = torch.autograd.grad(gan_loss, last_layer, retain_graph=True)[0]
    weight = rec_grad.float().norm() / (gan_grad.float().norm() + 1e-4)
    return weight.clamp(0.0, max_weight).detach() * disc_weight


class LeCAM(nn.Module):
    """LeCAM regularizer (Tseng et al. 2021) with EMAs of the mean real and fake logits, kept as buffers so they
    are saved with the training state.

    reg = mean(relu(real - ema_fake)^2) + mean(relu(ema_real - fake)^2)
    """

    def __init__(self, decay: float = 0.999):
        super().__init__()
        self.decay = decay
        self.register_buffer("ema_real", torch.zeros(()))
        self.register_buffer("ema_fake", torch.zeros(()))

    @torch.no_grad()
    def update(self, logits_real: torch.Tensor, logits_fake: torch.Tensor) -> None:
        self.ema_real.lerp_(logits_real.float().mean(), 1 - self.decay)
        self.ema_fake.lerp_(logits_fake.float().mean(), 1 - self.decay)

    def forward(self, logits_real: torch.Tensor, logits_fake: torch.Tensor) -> torch.Tensor:
        return (F.relu(logits_real.float() - self.ema_fake).pow(2).mean()
                + F.relu(self.ema_real - logits_fake.float()).pow(2).mean())


class VQLoss(nn.Module):
    """All tokenizer losses, weighted by the VQConfig fields.

    generator loss = l1_weight * |x - x_rec| + perceptual_weight * LPIPS(x, x_rec)
                     + g_weight * GAN_g(D(x_rec))                          (from step disc_start, when use_gan)
                     + commitment_weight * commit + entropy_weight * entropy
    with g_weight = adaptive_generator_weight(...) * disc_weight (gan_weighting "adaptive") or gen_loss_weight
    ("fixed", as the published Open-MAGVIT2 configs do).
    discriminator loss = GAN_d(D(x), D(x_rec)) + lecam_weight * LeCAM(D(x), D(x_rec))

    perceptual: a frozen `magvit2.lpips.LPIPS` or None (then no perceptual term). `perceptual_every` computes
    LPIPS on every n-th generator step only (a CPU speed knob; the term is skipped, not rescaled, in between).
    """

    def __init__(self, config: VQConfig, perceptual: Optional[nn.Module] = None, use_gan: bool = False,
                 gan_loss: str = "hinge", gan_weighting: str = "adaptive", disc_channels: int = 64,
                 disc_layers: int = 3, perceptual_every: int = 1, lecam_decay: float = 0.999):
        super().__init__()
        if gan_loss not in GAN_LOSSES:
            raise ValueError(f"gan_loss must be one of {GAN_LOSSES}, got {gan_loss!r}")
        if gan_weighting not in GAN_WEIGHTINGS:
            raise ValueError(f"gan_weighting must be one of {GAN_WEIGHTINGS}, got {gan_weighting!r}")
        if perceptual_every < 1:
            raise ValueError(f"perceptual_every must be >= 1, got {perceptual_every}")
        self.config = config
        self.perceptual = perceptual if config.perceptual_weight > 0 else None
        self.perceptual_every = perceptual_every
        self.use_gan = use_gan
        self.gan_weighting = gan_weighting
        self.d_loss_fn = hinge_d_loss if gan_loss == "hinge" else non_saturating_d_loss
        self.g_loss_fn = hinge_g_loss if gan_loss == "hinge" else non_saturating_g_loss
        self.discriminator = (NLayerDiscriminator(config.out_channels, disc_channels, disc_layers)
                              if use_gan else None)
        self.lecam = LeCAM(lecam_decay)

    def gan_active(self, step: int) -> bool:
        return self.use_gan and step >= self.config.disc_start

    def reconstruction_loss(self, x_B3HW: torch.Tensor, x_rec_B3HW: torch.Tensor,
                            step: int) -> Tuple[torch.Tensor, Dict[str, torch.Tensor]]:
        """Weighted L1 + LPIPS (the 'nll' of VQGAN), plus its parts for logging."""
        l1 = (x_B3HW.float() - x_rec_B3HW.float()).abs().mean()
        loss = self.config.l1_weight * l1
        logs = {"l1": l1.detach()}
        if self.perceptual is not None and step % self.perceptual_every == 0:
            p_loss = self.perceptual(x_rec_B3HW, x_B3HW).mean()
            loss = loss + self.config.perceptual_weight * p_loss
            logs["lpips"] = p_loss.detach()
        return loss, logs

    def generator_loss(self, x_B3HW: torch.Tensor, x_rec_B3HW: torch.Tensor, quant: LFQOutput, step: int,
                       last_layer: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, Dict[str, torch.Tensor]]:
        """Autoencoder loss for one batch. last_layer: the decoder's output conv weight (adaptive weighting)."""
        cfg = self.config
        rec_loss, logs = self.reconstruction_loss(x_B3HW, x_rec_B3HW, step)
        loss = (rec_loss + cfg.commitment_weight * quant.commit_loss.float()
                + cfg.entropy_weight * quant.entropy_loss.float())
        logs.update(commit=quant.commit_loss.detach(), entropy=quant.entropy_loss.detach(),
                    per_sample_entropy=quant.per_sample_entropy.detach(),
                    codebook_entropy=quant.codebook_entropy.detach())
        if self.gan_active(step):
            self.discriminator.requires_grad_(False)  # the generator step must not touch D's gradients
            g_loss = self.g_loss_fn(self.discriminator(x_rec_B3HW).float())
            self.discriminator.requires_grad_(True)
            g_weight = self._generator_weight(rec_loss, g_loss, last_layer)
            loss = loss + g_weight * g_loss
            logs.update(g_loss=g_loss.detach(), g_weight=g_weight.detach())
        logs["loss"] = loss.detach()
        return loss, logs

    def _generator_weight(self, rec_loss: torch.Tensor, g_loss: torch.Tensor,
                          last_layer: Optional[torch.Tensor]) -> torch.Tensor:
        if self.gan_weighting == "fixed" or not torch.is_grad_enabled():
            return torch.tensor(self.config.gen_loss_weight, device=g_loss.device)
        if last_layer is None:
            raise ValueError("adaptive GAN weighting needs last_layer (the decoder's conv_out.weight)")
        return adaptive_generator_weight(rec_loss, g_loss, last_layer, self.config.disc_weight)

    def discriminator_loss(self, x_B3HW: torch.Tensor, x_rec_B3HW: torch.Tensor, step: int,
                           discriminator: Optional[nn.Module] = None) -> Tuple[torch.Tensor, Dict[str, torch.Tensor]]:
        """Discriminator loss on real x and (detached) reconstructions; updates the LeCAM EMAs.

        discriminator: the module to run, e.g. the DistributedDataParallel wrapper of `self.discriminator` that
        synchronizes its gradients (default: `self.discriminator`).
        """
        if not self.gan_active(step):
            state = "off" if not self.use_gan else f"inactive before disc_start={self.config.disc_start}"
            raise RuntimeError(f"discriminator_loss called at step {step}, but the GAN is {state}")
        # Separate passes: BatchNorm statistics of one batch must not mix real and fake images.
        discriminator = discriminator if discriminator is not None else self.discriminator
        logits_real = discriminator(x_B3HW).float()
        logits_fake = discriminator(x_rec_B3HW.detach()).float()
        d_loss = self.d_loss_fn(logits_real, logits_fake)
        loss = d_loss
        logs = {"d_loss": d_loss.detach(), "logits_real": logits_real.detach().mean(),
                "logits_fake": logits_fake.detach().mean()}
        if self.config.lecam_weight > 0:
            self.lecam.update(logits_real, logits_fake)
            lecam = self.lecam(logits_real, logits_fake)
            loss = loss + self.config.lecam_weight * lecam
            logs["lecam"] = lecam.detach()
        return loss, logs
