"""What `mitsuba_reference.py` and `cycles_reference.py` share: image means over blocks, and the
comparison of two renderers' passes against the passes' own noise."""

import numpy as np


def block_means(image, blocks):
    """Per-channel means of the whole image and of a blocks × blocks grid of tiles."""
    h, w, _ = image.shape
    rows = np.array_split(np.arange(h), blocks)
    cols = np.array_split(np.arange(w), blocks)
    tiles = [image[np.ix_(r, c)].reshape(-1, 3).mean(axis=0) for r in rows for c in cols]
    return np.vstack([image.reshape(-1, 3).mean(axis=0)] + tiles)


def report(scene, spp, means, ours, theirs, blocks):
    """Prints the difference of the passes' means (`means[name]`: one `block_means` per pass) in
    units of its standard error, whole image and per block."""
    m = {k: np.array(v) for k, v in means.items()}  # passes × (1 + blocks²) × 3
    passes = len(m[ours])
    mean = {k: v.mean(axis=0) for k, v in m.items()}
    error = {k: v.std(axis=0, ddof=1) / np.sqrt(passes) for k, v in m.items()}
    difference = mean[ours] - mean[theirs]
    noise = np.sqrt(error[ours] ** 2 + error[theirs] ** 2)
    # Blocks of background alone are exact in both (every path escapes at once): no noise, and
    # equal values give z = 0; a difference there is infinitely significant.
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(noise > 0, difference / noise, np.where(difference == 0, 0.0, np.inf))
        relative = np.where(mean[theirs] != 0, difference / mean[theirs], 0.0)
    print(f"{scene}: {passes} passes of {spp} spp per renderer")
    for c, name in enumerate("RGB"):
        print(
            f"  {name}: image mean {ours} {mean[ours][0, c]:.5f} ± {error[ours][0, c]:.5f}, "
            f"{theirs} {mean[theirs][0, c]:.5f} ± {error[theirs][0, c]:.5f} "
            f"({100 * relative[0, c]:+.2f} %, z = {z[0, c]:+.2f})"
        )
    print(
        f"  {blocks}×{blocks} blocks × 3 channels: |z| ≤ {np.abs(z[1:]).max():.2f} "
        f"(largest relative difference {100 * np.abs(relative[1:]).max():.2f} %)"
    )
    print("  z per block (channel of largest |z|):")
    worst = np.abs(z[1:]).max(axis=1).reshape(blocks, blocks)
    for row in worst:
        print("   " + " ".join(f"{v:5.2f}" for v in row))
