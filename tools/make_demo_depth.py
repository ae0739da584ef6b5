"""Writes examples/data/depths/chelsea.npy: a smooth synthetic depth for the bundled demo photo.

Disparity = a slanted background (nearer at the bottom) plus a Gaussian bump around the cat's
head; depth = 1 / disparity. It is a stand-in so the demo runs without a depth model; real use
wants a depth model or measured depth.
"""
import numpy as np

h, w = 300, 451
y, x = np.mgrid[0:h, 0:w].astype(np.float64)
s, t = x / (w - 1), y / (h - 1)
disp = 0.25 + 0.35 * t + 0.35 * np.exp(-(((s - 0.52) / 0.22) ** 2 + ((t - 0.42) / 0.3) ** 2))
np.save("examples/data/depths/chelsea.npy", (1.0 / disp).astype(np.float32))
