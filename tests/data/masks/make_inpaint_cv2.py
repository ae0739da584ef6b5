"""Writes the cv2.inpaint (INPAINT_TELEA) comparison cases used by tests/samples/inpaint.rs.

Run with numpy and opencv-python-headless installed (used: opencv-python-headless 5.0.0):
    python make_inpaint_cv2.py
Each case NAME gives NAME_in.npy (image), NAME_mask.npy (u8, 1 = fill) and NAME_out.npy
(cv2.inpaint(image, mask, radius, cv2.INPAINT_TELEA)); the radius is in the case list below and
in tests/samples/inpaint.rs.
"""
import cv2
import numpy as np

rng = np.random.default_rng(7)


def smooth(h, w, c):
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    chans = [120 + 60 * np.sin(x / 7.0 + k) + 40 * np.cos(y / 5.0 - 0.5 * k) + 10 * rng.standard_normal((h, w))
             for k in range(c)]
    return np.clip(np.stack(chans, -1), 0, 255)


def hole(h, w):
    m = np.zeros((h, w), np.uint8)
    cv2.circle(m, (w // 2, h // 2), min(h, w) // 4, 1, -1)
    m[0:4, 3:9] = 1  # touching the top border
    m[h - 6:h, w - 3:w] = 1  # the bottom-right corner
    m[10:12, 0:5] = 1  # the left border
    m[rng.random((h, w)) < 0.03] = 1  # scattered single pixels
    return m


# name: (height, width, channels, dtype, radius)
CASES = {
    "inpaint_gray_u8_r3": (30, 40, 1, np.uint8, 3),
    "inpaint_rgb_u8_r5": (32, 40, 3, np.uint8, 5),
    "inpaint_gray_f32_r3": (30, 40, 1, np.float32, 3),
}
for name, (h, w, c, dtype, radius) in CASES.items():
    img = smooth(h, w, c)
    img = img.astype(np.uint8) if dtype == np.uint8 else (img / 255.0).astype(np.float32)
    if c == 1:
        img = img[..., 0]
    m = hole(h, w)
    out = cv2.inpaint(img, m, radius, cv2.INPAINT_TELEA)
    np.save(f"{name}_in.npy", img)
    np.save(f"{name}_mask.npy", m)
    np.save(f"{name}_out.npy", out)
    print(name, img.shape, img.dtype, "hole pixels", int(m.sum()), "cv2", cv2.__version__)
