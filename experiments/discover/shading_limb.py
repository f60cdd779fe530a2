import sys; sys.path.insert(0, "/work/main/tests")
import numpy as np, torch
from torchfit.video import _segment, SegmentationSettings, raw_moments
from torchfit.losses import central_moments

def frames_of(blur_px, shaded, speed=10.0, radius=12.0, samples=4, steps=21, frames=16, noise=0.0, seed=0):
    height, width = 100, 260
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    scene = np.stack([90 + 0.2 * xx, 100 + 0.3 * yy, 120 - 0.1 * xx], -1)
    colour = np.array([60.0, 140.0, 200.0])
    ys, xs = np.mgrid[0:height * samples, 0:width * samples] / samples + 0.5 / samples - 0.5
    rng = np.random.default_rng(seed)
    images, covers = [], []
    for t in range(frames):
        acc_cover = np.zeros_like(xs); acc_light = np.zeros(xs.shape + (3,))
        for k in range(steps):
            cx = 20 + speed * t + (k / (steps - 1) - 0.5) * blur_px
            r2 = ((xs - cx) ** 2 + (ys - 50) ** 2) / radius**2
            inside = r2 <= 1
            shade = np.sqrt(np.clip(1 - r2, 0, 1)) * 0.7 + 0.3 if shaded else np.ones_like(r2)  # Lambertian, light from the camera
            acc_cover += inside
            acc_light += (inside * shade)[..., None] * colour
        cover = acc_cover / steps
        obj = acc_light / steps
        light = obj + (1 - cover)[..., None] * np.repeat(np.repeat(scene, samples, 0), samples, 1)
        light = light.reshape(height, samples, width, samples, 3).mean((1, 3))
        img = np.clip(np.round(light + rng.normal(0, noise, light.shape)), 0, 255).astype(np.uint8)
        images.append(img); covers.append(cover.reshape(height, samples, width, samples).mean((1, 3)))
    return np.array(images), np.array(covers)

for shaded in ():
    for blur in (0.0, 5.0, 10.0, 15.0):
        f, c = frames_of(blur, shaded, speed=max(blur, 10.0))
        inner = slice(3, -3)
        ex = central_moments(torch.as_tensor(raw_moments(c[inner])))
        for band in ("steps", "motion"):
            out = _segment(f, SegmentationSettings(albedo_passes=1, coverage_band=band, coverage_clip=False))
            ob = central_moments(torch.as_tensor(out["coverage_moments"][inner]))
            d = (ob[2] - ex[2]).mean(0).numpy()
            print(f"shaded={shaded!s:5} blur={blur:4.1f} band={band:6s} area {float((ob[0]/ex[0]).mean()):.4f} along {d[0,0]:+.2f} across {d[1,1]:+.2f} px^2")
print("shading_radius variants, shaded sphere")
for radius in (0.0, 0.75, 1.5, 3.0):
    for blur in (0.0, 10.0):
        f, c = frames_of(blur, True, speed=10.0)
        inner = slice(3, -3)
        ex = central_moments(torch.as_tensor(raw_moments(c[inner])))
        out = _segment(f, SegmentationSettings(albedo_passes=1, coverage_band="motion", coverage_clip=False, shading_radius=radius))
        ob = central_moments(torch.as_tensor(out["coverage_moments"][inner]))
        d = (ob[2] - ex[2]).mean(0).numpy()
        print(f"radius={radius} blur={blur:4.1f} area {float((ob[0]/ex[0]).mean()):.4f} along {d[0,0]:+.2f} across {d[1,1]:+.2f} px^2")
