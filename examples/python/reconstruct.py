"""The quick ball (scenes/inverse/quick.toml) reconstructed in PyTorch: Adam on the density, an L2
image loss and a total-variation prior written in PyTorch, volgrad's joint gradient underneath.

    .venv/bin/python examples/python/reconstruct.py [ITERATIONS]
"""

import pathlib
import sys

import numpy as np
import torch

import volgrad
import volgrad.torch

SCENES = pathlib.Path(__file__).resolve().parents[2] / "scenes" / "inverse"


def psnr(image, target):  # as volgrad's log: the target's peak, the mean over views
    return float(np.mean([10 * np.log10(t.max() ** 2 / ((i - t) ** 2).mean()) for i, t in zip(image, target)]))


def reconstruct(iterations=150, seed=0, log=print):
    scene = volgrad.Scene.load(SCENES / "quick-scene.toml")  # lights, medium, the true grid
    truth, index_to_world = scene.density
    train = volgrad.Camera.orbit(8, 12.0, elevation_deg=(-30, 70), width=32, height=32)
    held_out = volgrad.Camera.orbit(2, 12.0, elevation_deg=(0, 40), width=32, height=32, azimuth_offset_deg=60)
    targets = torch.from_numpy(scene.render(train, spp=256, seed=1))
    held_out_targets = scene.render(held_out, spp=256, seed=2)
    # Step sizes in optical depth along the box, as `optimize` derives them: 0.5 per step at first.
    edge = np.abs(index_to_world[:3, :3]).max() * max(truth.shape)
    unit = 1.0 / (0.6 * edge)  # density_scale 0.6: the value whose optical depth along the box is 1
    density = torch.zeros(truth.shape, requires_grad=True)
    adam = torch.optim.Adam([density], lr=0.5 * unit)
    decay = torch.optim.lr_scheduler.ExponentialLR(adam, gamma=0.1 ** (1 / iterations))
    power = (targets**2).mean()  # the prior's weight is relative to the images' power, as in a run file
    rng = np.random.default_rng(seed)
    for i in range(iterations):
        batch = rng.choice(len(train), 4, replace=False)
        images = volgrad.torch.render(
            density, scene, [train[j] for j in batch], spp=16, grad_spp=8, seed=1000 * seed + i
        )
        image_loss = ((images - targets[batch]) ** 2).mean()
        tv = sum((density.diff(dim=d)).abs().mean() for d in range(3)) / unit
        loss = image_loss + 1.03e-4 * power * tv
        adam.zero_grad()
        loss.backward()
        adam.step()
        decay.step()
        with torch.no_grad():
            density.clamp_(min=0)
        if (i + 1) % 25 == 0 or i + 1 == iterations:
            held = scene.render(held_out, spp=256, seed=3, density=density.detach().numpy())
            log(f"iteration {i + 1:4d}  loss {loss.item():.3e}  held-out PSNR {psnr(held, held_out_targets):.2f} dB")
    return density.detach().numpy(), psnr(held, held_out_targets)


if __name__ == "__main__":
    reconstruct(int(sys.argv[1]) if len(sys.argv) > 1 else 150)
