"""Tests of the video front end (torchfit.video) on the shipped MuJoCo recordings."""
from __future__ import annotations

import json
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from scipy import ndimage

from torchfit.camera import Camera
from torchfit.losses import central_moments
from torchfit.video import (
    Observation,
    SegmentationSettings,
    _decode,
    _h264_sps_transfer,
    _iso_boxes,
    _read_moov,
    _segment,
    _undistort,
    _undistort_maps,
    contact_sheet,
    load_observation,
    motion_band,
    raw_moments,
    read_frames,
    stored_transfer,
)

DATA = Path(__file__).resolve().parents[1] / "torchfit" / "recordings"
SHIPPED = ["tshape", "tshape_intermediate", "box_fast", "cylinder", "tshape_small"]


def true_masks(name: str) -> np.ndarray:
    with np.load(DATA / name / "masks.npz") as archive:
        return archive["masks"].astype(bool)


def iou(masks: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(T,) intersection over union of two (T, H, W) bool stacks."""
    union = (masks | truth).sum(axis=(1, 2))
    return (masks & truth).sum(axis=(1, 2)) / np.maximum(union, 1)


@pytest.fixture(scope="module")
def observations() -> dict[str, Observation]:
    return {name: load_observation(DATA / name / "video.mp4", camera=DATA / name / "camera.json")
            for name in SHIPPED}


def write_video(path: Path, frames: np.ndarray, fps: float = 30.0) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps,
                             (frames.shape[2], frames.shape[1]))
    for frame in frames:
        writer.write(frame)
    writer.release()
    return path


# --- segmentation quality ------------------------------------------------------------

# (median, worst frame) floors, a little under the figures experiments/segmentation_iou.py
# measures (H.264, crf 14, 4:2:0): tshape 0.949/0.911, tshape_intermediate 0.960/0.910,
# box_fast 0.972/0.946, cylinder 0.976/0.956, tshape_small 0.965/0.955
FLOORS = {
    "tshape": (0.94, 0.90),
    "tshape_intermediate": (0.95, 0.90),
    "box_fast": (0.96, 0.93),
    "cylinder": (0.96, 0.94),
    "tshape_small": (0.95, 0.94),
}


@pytest.mark.parametrize("name", SHIPPED)
def test_segmentation_iou(observations, name):
    """The issue's target: IoU >= 0.9 on every frame of every shipped recording, and the floors."""
    obs = observations[name]
    truth = true_masks(name)
    scores = iou(obs.masks, truth)[obs.used]
    median_floor, worst_floor = FLOORS[name]
    assert obs.used.all()
    assert np.median(scores) >= median_floor
    assert scores.min() >= max(worst_floor, 0.9)


def _blurred_disc_frames(frames=16, blur_px=10.0, radius=12.0, samples=4, steps=21,
                         colour=(60.0, 140.0, 200.0), background=(90.0, 100.0, 120.0), transfer="linear",
                         limb=None):
    """(T, H, W, 3) uint8 BGR frames of a disc moving 10 px a frame along x over a smooth coloured
    background, blurred by ``blur_px`` of travel (``steps`` positions averaged, each pixel
    ``samples`` x ``samples`` sub-samples), no noise; and (T, H, W) its exact coverage. ``limb``:
    the disc shaded as a Lambertian sphere lit from the camera, ``limb`` of its centre's
    brightness at its edge (None: flat).

    ``colour`` and ``background`` (the background's value at the top left) are stored values; the
    blur and the partial coverage mix them in the light that ``transfer`` decodes them to, and the
    mix is encoded back with it (to the nearest code), as a camera does."""
    height, width = 100, 200
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    scene = np.stack([background[0] + 0.2 * xx, background[1] + 0.3 * yy, background[2] - 0.1 * xx], -1)
    scene, colour = (_decode(np.asarray(v, np.float64), transfer).astype(np.float64) for v in (scene, colour))
    codes = _decode(np.arange(256, dtype=np.float64), transfer).astype(np.float64)  # light of each code
    ys, xs = np.mgrid[0:height * samples, 0:width * samples] / samples + 0.5 / samples - 0.5
    images, covers = [], []
    for t in range(frames):
        r2 = [((xs - (20 + 10 * t + (k / (steps - 1) - 0.5) * blur_px)) ** 2 + (ys - 50) ** 2) / radius**2
              for k in range(steps)]
        inside = sum(r <= 1 for r in r2) / steps
        shade = 1.0 if limb is None else sum((r <= 1) * (limb + (1 - limb) * np.sqrt(np.clip(1 - r, 0, 1)))
                                             for r in r2) / steps
        cover = inside.reshape(height, samples, width, samples).mean((1, 3))
        shade = shade if limb is None else shade.reshape(height, samples, width, samples).mean((1, 3))
        light = (shade if limb is not None else cover)[..., None] * colour + (1 - cover[..., None]) * scene
        above = np.clip(np.searchsorted(codes, light), 1, 255)  # the nearest code's light
        images.append(np.where(light - codes[above - 1] < codes[above] - light, above - 1, above).astype(np.uint8))
        covers.append(cover)
    return np.array(images), np.array(covers)


@pytest.mark.parametrize("passes, unbiased", [(0, False), (1, True)])
def test_albedo_from_covered_pixels_leaves_a_blurred_edge_unbiased(monkeypatch, passes, unbiased):
    """On a blurred disc most eroded seed pixels are partly covered; an albedo taken from all of
    them tilts toward the background and the per-pixel coverage on the blurred ramp reads high
    (measured +0.08 with no refit pass). Re-estimated from the pixels the first pass calls
    covered (``SegmentationSettings.albedo_passes = 1``; off by default, see its docstring), it is
    within 0.01 of the exact coverage."""
    import torchfit.video as video

    frames, covers = _blurred_disc_frames()
    kept = []
    original = video._local_shading_coverage

    def watch(diff, background, albedo, coverage, *rest):
        kept.append(coverage.copy())
        return original(diff, background, albedo, coverage, *rest)

    monkeypatch.setattr(video, "_local_shading_coverage", watch)
    video._segment(frames, SegmentationSettings(albedo_passes=passes))
    ramp = (covers > 0.05) & (covers < 0.95)
    ramp[:2] = ramp[-2:] = False  # the first and last frames' background median is the weakest
    bias = float((np.array(kept) - covers)[ramp].mean())
    assert (abs(bias) < 0.01) if unbiased else (bias > 0.05), bias


@pytest.mark.parametrize("transfer, follows", [("linear", False), ("srgb", True)])
def test_decoded_light_keeps_a_blurred_dark_disc_its_size(transfer, follows):
    """A camera sums light and then encodes it (here with the sRGB curve). Read as it is stored
    (``transfer="linear"``) a blurred edge of a dark disc on a light background reads too little
    coverage, and the more the longer its blur: the mask shrinks with the speed (measured -15 px
    at rest, -81 px at 8 px of blur, of 452). Decoded to light first it keeps its size. (One
    albedo pass, ``albedo_passes=1``, takes out the albedo's own blur bias, which grows the mask.)"""
    areas = []
    for blur_px in (0.0, 8.0):
        frames, _ = _blurred_disc_frames(frames=10, blur_px=blur_px, colour=(40.0, 60.0, 70.0),
                                         background=(170.0, 180.0, 200.0), transfer="srgb")
        masks = _segment(frames, SegmentationSettings(transfer=transfer, albedo_passes=1))["masks"]
        areas.append(float(masks[2:-2].sum((1, 2)).mean()))  # the first and last frames' background is the weakest
    shrink = areas[0] - areas[1]
    assert (abs(shrink) < 5.0) if follows else (shrink > 30.0), areas


def test_decode_inverts_the_encoding_curves():
    light = np.linspace(0.0, 1.0, 11)
    srgb = np.where(light <= 0.0031308, 12.92 * light, 1.055 * light ** (1 / 2.4) - 0.055)
    bt709 = np.where(light < 0.018, 4.5 * light, 1.099 * light**0.45 - 0.099)
    a, b, c = 0.17883277, 0.28466892, 0.55991073  # BT.2100 hybrid log-gamma
    hlg = np.where(light <= 1 / 12, np.sqrt(3 * light), a * np.log(np.maximum(12 * light - b, 1e-12)) + c)
    for transfer, encoded in (("srgb", srgb), ("bt709", bt709), ("hlg", hlg)):
        assert np.allclose(_decode(255.0 * encoded, transfer), 255.0 * light, atol=1e-3)
        table = _decode(np.arange(256, dtype=np.uint8), transfer)  # the uint8 table, same curve
        assert np.allclose(table, _decode(np.arange(256, dtype=np.float64), transfer))
    for as_is in ("linear", "auto"):  # "auto" without a file to name a curve: the values as they are
        assert np.array_equal(_decode(np.arange(256, dtype=np.uint8), as_is), np.arange(256))
    with pytest.raises(ValueError, match="transfer"):
        SegmentationSettings(transfer="gamma")


def _box(kind: bytes, payload: bytes) -> bytes:
    return (8 + len(payload)).to_bytes(4, "big") + kind + payload


def _mp4(children: bytes) -> bytes:
    """A minimal MP4: ftyp, media data, then moov with a sound track (whose sample entry holds a
    'colr' naming PQ, which must not be read) and a video track, trak/mdia(hdlr)/minf/stbl/stsd with
    one 'avc1' sample entry (78 header bytes) holding ``children`` boxes."""
    def track(handler: bytes, entry: bytes) -> bytes:
        stsd = _box(b"stsd", bytes(4) + (1).to_bytes(4, "big") + entry)
        hdlr = _box(b"hdlr", bytes(8) + handler + bytes(12))
        return _box(b"trak", _box(b"mdia", hdlr + _box(b"minf", _box(b"stbl", stsd))))

    sound = track(b"soun", _box(b"mp4a", bytes(78) + _colr(16)))
    video = track(b"vide", _box(b"avc1", bytes(78) + children))
    return _box(b"ftyp", b"isom" + bytes(4)) + _box(b"mdat", bytes(64)) + _box(b"moov", sound + video)


def _colr(transfer: int, kind: bytes = b"nclx") -> bytes:
    return _box(b"colr", kind + (1).to_bytes(2, "big") + transfer.to_bytes(2, "big") + (1).to_bytes(2, "big")
                + (b"\0" if kind == b"nclx" else b""))


def _sps(transfer: int | None) -> bytes:
    """An H.264 High-profile sequence parameter set NAL (emulation prevention applied) whose VUI
    names ``transfer``, or that has no VUI (None)."""
    fields = []

    def u(value, n):
        fields.append(format(value, f"0{n}b") if n else "")

    def ue(value):
        code = format(value + 1, "b")
        fields.append("0" * (len(code) - 1) + code)

    u(100, 8), u(0, 8), u(40, 8), ue(0)  # profile High, constraints, level, sps id
    ue(1), ue(0), ue(0), u(0, 1), u(0, 1)  # 4:2:0, 8-bit, 8-bit, no bypass, no scaling matrix
    ue(0), ue(0), ue(2), ue(4), u(0, 1), ue(39), ue(29), u(1, 1), u(1, 1), u(0, 1)
    u(transfer is not None, 1)  # vui_parameters_present
    if transfer is not None:
        u(0, 1), u(0, 1), u(1, 1), u(5, 3), u(0, 1), u(1, 1), u(1, 8), u(transfer, 8), u(1, 8)
    bits = "".join(fields) + "1"
    raw = int(bits.ljust(-(-len(bits) // 8) * 8, "0"), 2).to_bytes(-(-len(bits) // 8), "big")
    nal, zeros = bytearray([0x67]), 0
    for byte in raw:
        if zeros >= 2 and byte <= 3:
            nal.append(3)
            zeros = 0
        nal.append(byte)
        zeros = zeros + 1 if byte == 0 else 0
    return bytes(nal)


def _avcc(sps: bytes) -> bytes:
    return _box(b"avcC", bytes([1, 100, 0, 40, 0xFF, 0xE1]) + len(sps).to_bytes(2, "big") + sps)


@pytest.mark.parametrize("children, expected", [
    (_colr(1), "bt709"), (_colr(1, b"nclc"), "bt709"), (_colr(13), "srgb"), (_colr(18), "hlg"),
    (_colr(8), "linear"), (_colr(2), "linear"), (_avcc(_sps(1)), "bt709"), (_avcc(_sps(13)), "srgb"),
    (_avcc(_sps(None)), "linear"), (_colr(13) + _avcc(_sps(1)), "srgb"), (b"", "linear")])
def test_stored_transfer_reads_an_mp4_colour_tag(tmp_path, children, expected):
    """The curve a file names: its sample entry's 'colr' box, else its H.264 VUI; none named is
    read as linear (torchfit's own recordings name none)."""
    path = tmp_path / "clip.mp4"
    path.write_bytes(_mp4(children))
    transfer, note = stored_transfer(path)
    assert transfer == expected, note
    assert ("no transfer curve named" in note) == (children in (_colr(2), _avcc(_sps(None)), b""))


def test_stored_transfer_refuses_a_curve_it_cannot_decode(tmp_path):
    path = tmp_path / "hdr.mov"
    path.write_bytes(_mp4(_colr(16)))
    with pytest.raises(ValueError, match=r"transfer 16 \(PQ"):
        stored_transfer(path)


def test_stored_transfer_on_real_encoder_output():
    """libx264's own parameter sets, read through the same path: a file tagged sRGB by FFmpeg
    (tests/data/tagged_srgb.mp4, 16 x 16, made with PyAV, color_trc 13) in its 'colr' box and in its
    VUI; the shipped recordings name no curve and are read as linear."""
    tagged = Path(__file__).parent / "data" / "tagged_srgb.mp4"
    assert stored_transfer(tagged)[0] == "srgb"
    for path, code in ((tagged, 13), (DATA / "tshape" / "video.mp4", None)):
        boxes = dict(_iso_boxes(_read_moov(path)))
        for kind in (b"trak", b"mdia", b"minf", b"stbl"):
            boxes = dict(_iso_boxes(boxes[kind]))
        avcc = dict(_iso_boxes(dict(_iso_boxes(boxes[b"stsd"][8:]))[b"avc1"][78:]))[b"avcC"]
        assert _h264_sps_transfer(avcc[8:8 + int.from_bytes(avcc[6:8], "big")]) == code
    transfer, note = stored_transfer(DATA / "tshape" / "video.mp4")
    assert transfer == "linear" and "no transfer curve named (H.264 stream's VUI)" in note


def _tag_png(path: Path, chunk: bytes | None) -> Path:
    """Insert ``chunk`` (type + data) after a PNG file's header chunk."""
    if chunk is not None:
        data = path.read_bytes()
        end = 8 + 12 + int.from_bytes(data[8:12], "big")  # past the signature and IHDR
        block = (len(chunk) - 4).to_bytes(4, "big") + chunk + zlib.crc32(chunk).to_bytes(4, "big")
        path.write_bytes(data[:end] + block + data[end:])
    return path


def _png_with(chunk: bytes | None, path: Path) -> Path:
    """A 4 x 4 grey PNG with ``chunk`` inserted after its header chunk."""
    cv2.imwrite(str(path), np.full((4, 4, 3), 128, np.uint8))
    return _tag_png(path, chunk)


def test_stored_transfer_reads_image_folders(tmp_path):
    cases = {"srgb": (b"sRGB\0", "srgb"), "cicp": (b"cICP" + bytes([1, 18, 0, 1]), "hlg"),
             "linear": (b"gAMA" + (100000).to_bytes(4, "big"), "linear"),
             "gamma22": (b"gAMA" + (45455).to_bytes(4, "big"), "srgb"), "none": (None, "linear")}
    for name, (chunk, expected) in cases.items():
        (tmp_path / name).mkdir()
        _png_with(chunk, tmp_path / name / "000.png")
        assert stored_transfer(tmp_path / name)[0] == expected, name
    (tmp_path / "odd").mkdir()
    _png_with(b"gAMA" + (50000).to_bytes(4, "big"), tmp_path / "odd" / "000.png")
    with pytest.raises(ValueError, match="gAMA"):
        stored_transfer(tmp_path / "odd")
    (tmp_path / "jpeg").mkdir()
    cv2.imwrite(str(tmp_path / "jpeg" / "000.jpg"), np.full((4, 4, 3), 128, np.uint8))
    assert stored_transfer(tmp_path / "jpeg") == ("srgb", "000.jpg: JPEG stores sRGB")


def test_auto_transfer_decodes_what_the_file_names(tmp_path):
    """``transfer="auto"`` (the default): an image folder whose PNGs carry an sRGB chunk is segmented
    as ``transfer="srgb"`` (the same masks), the observation says so; the same frames without the
    chunk are read as linear."""
    frames, _ = _blurred_disc_frames(frames=8, blur_px=8.0, colour=(40.0, 40.0, 40.0),
                                     background=(170.0, 180.0, 200.0), transfer="srgb")
    for tagged in (True, False):
        folder = tmp_path / f"tagged_{tagged}"
        folder.mkdir()
        for i, frame in enumerate(frames):
            cv2.imwrite(str(folder / f"{i:03d}.png"), frame)
            _tag_png(folder / f"{i:03d}.png", b"sRGB\0" if tagged else None)
        observation = load_observation(folder, fps=30.0)
        expected = "srgb" if tagged else "linear"
        assert observation.transfer == expected, observation.transfer_note
        explicit = load_observation(folder, fps=30.0, settings=SegmentationSettings(transfer=expected))
        assert np.array_equal(observation.masks, explicit.masks)
    assert "sRGB chunk" in load_observation(tmp_path / "tagged_True", fps=30.0).transfer_note


def _shaded_bar_scene(frames=15, height=60, width=200, grey_half=True, texture=6.0, seed=0):
    """A wooden bar with a lit face and a shaded one (0.45 of the lit one's light) moving right
    over a dark green background (``|B|`` ~45 grey levels, ``|B| sin(angle(A, B))`` ~7, the
    concealed recordings' dark grass), its left half grey when ``grey_half``, with a Gaussian
    ``texture`` (grey levels; none at 0).

    Returns (T, H, W, 3) uint8 BGR frames and (T, H, W) exact coverage.
    """
    rng = np.random.default_rng(seed)
    sub = 4  # supersampling of the partial pixel coverage
    yy, xx = (np.mgrid[:height * sub, :width * sub] + 0.5) / sub - 0.5
    background = np.empty((height, width, 3))
    background[:] = (22, 38, 26)
    if grey_half:
        background[:, : width // 2] = (110, 120, 125)
    if texture > 0:
        background += rng.normal(0, texture, background.shape)
    albedo = np.array([82.0, 115.0, 148.0])  # wood, BGR
    images, coverages = [], []
    for t in range(frames):
        x0 = 5 + 10 * t
        inside = (xx >= x0) & (xx < x0 + 40) & (yy >= 18.3) & (yy < 40.6)
        shade = np.where(yy < 29.4, 1.0, 0.45)
        coverage = inside.reshape(height, sub, width, sub).mean((1, 3))
        colour = (inside * shade).reshape(height, sub, width, sub).mean((1, 3))[..., None] * albedo
        image = background * (1 - coverage[..., None]) + colour + rng.normal(0, 2, background.shape)
        images.append(np.clip(np.round(image), 0, 255).astype(np.uint8))
        coverages.append(coverage)
    return np.stack(images), np.stack(coverages)


def test_local_shading_finds_a_shaded_face_over_a_dark_background():
    """Where the per-pixel fit is not trusted, the local shading still reads the face. The dark half
    (|B| sin(angle(A, B)) ~7 grey levels, textured) is trusted per pixel above 5 grey levels;
    trusted only above 10, the scene exercises the ill-posed case."""
    frames, coverage = _shaded_bar_scene()
    truth = coverage >= 0.5  # pixel centre inside
    local = _segment(frames, SegmentationSettings(well_posed_grey=10.0))["masks"]
    per_pixel = _segment(frames, SegmentationSettings(shading_radius=0.0, well_posed_grey=10.0))["masks"]
    assert iou(local, truth).min() >= 0.93
    assert iou(per_pixel, truth).min() < 0.7  # the scene exercises the ill-posed case


@pytest.mark.parametrize("grey, interior, keeps_the_face", [(5.0, False, True), (10.0, False, False),
                                                            (10.0, True, True)])
def test_a_shaded_face_over_dark_grass_is_kept(grey, interior, keeps_the_face):
    """Over a background whose colour off the albedo's direction is ~7 grey levels the per-pixel
    fit still reads the shaded face (its noise is 2 / 7 of a coverage per pixel, and the local
    shading averages it): trusted above 5 grey levels. Trusted only above 10, the
    face took its shading from the lit face beside it, read too little covered and was lost: the
    coverage's centroid 5 px high and its area half the truth's, as on the concealed recordings'
    dark faces over dark grass (experiments/discover/HISTORY.md, *Sixtieth session*). With the
    shading supported by the object's interior the face's own inside gives it its shading, and
    it is kept at 10 too."""
    frames, coverage = _shaded_bar_scene(frames=12, width=160, grey_half=False, texture=0.0)
    settings = SegmentationSettings(well_posed_grey=grey, interior_shading=interior)
    read = _segment(frames, settings)["coverage_moments"]
    exact = raw_moments(coverage)
    centroid_y = read[:, 2] / read[:, 0] - exact[:, 2] / exact[:, 0]  # (T,) px
    area = read[:, 0] / exact[:, 0] - 1.0  # (T,)
    if keeps_the_face:
        assert np.abs(centroid_y).max() < 0.3 and np.abs(area).max() < 0.15
    else:
        assert centroid_y.mean() < -4.0 and area.mean() < -0.4


@pytest.mark.parametrize("name", ["tshape", "box_fast"])
def test_boxes_and_fields(observations, name):
    obs = observations[name]
    truth = json.loads((DATA / name / "truth.json").read_text())
    T = len(obs.masks)
    assert obs.boxes.shape == (T, 4) and obs.used.shape == (T,) and len(obs.reasons) == T
    assert obs.fps == truth["fps"]
    np.testing.assert_array_equal(obs.frame_indices, np.arange(T))
    error = np.abs(obs.boxes - np.array(truth["per_frame"]["bbox"], float))  # (T, 4) pixels
    assert np.median(error) <= 1.5 and error.max() <= 5
    assert not obs.from_cache and obs.kind == "video"
    assert obs.background.shape == obs.masks.shape[1:] + (3,)


def test_mog2_background():
    name = "tshape_small"
    obs = load_observation(DATA / name / "video.mp4", method="mog2")
    assert np.median(iou(obs.masks, true_masks(name))) >= 0.5


# --- frame range, fps ----------------------------------------------------------------


def test_frame_range_and_fps_override():
    obs = load_observation(DATA / "tshape_small" / "video.mp4", start=2, stop=10, fps=25.0)
    assert obs.masks.shape[0] == 8 and obs.fps == 25.0
    np.testing.assert_array_equal(obs.frame_indices, np.arange(2, 10))
    np.testing.assert_allclose(obs.times, np.arange(8) / 25.0)


# --- cache ---------------------------------------------------------------------------


def test_cache(tmp_path):
    video = DATA / "tshape_small" / "video.mp4"
    first = load_observation(video, cache_dir=tmp_path)
    second = load_observation(video, cache_dir=tmp_path)
    assert not first.from_cache and second.from_cache
    np.testing.assert_array_equal(first.masks, second.masks)
    np.testing.assert_array_equal(first.boxes, second.boxes)
    np.testing.assert_array_equal(first.coverage_moments, second.coverage_moments)
    assert first.coverage_moments.shape == (len(first.masks), 6)
    assert first.reasons == second.reasons and first.fps == second.fps
    assert len(list(tmp_path.glob("*.npz"))) == 1
    other = load_observation(video, cache_dir=tmp_path, settings=SegmentationSettings(noise_sigmas=5))
    assert not other.from_cache  # the settings are part of the key
    camera = Camera.from_file(DATA / "tshape_small" / "camera.json")
    assert not load_observation(video, cache_dir=tmp_path, camera=camera).from_cache  # K registers the motion
    moved = Camera(camera.fx * 1.01, camera.fy * 1.01, camera.cx, camera.cy, camera.width, camera.height)
    assert not load_observation(video, cache_dir=tmp_path, camera=moved).from_cache
    assert load_observation(video, cache_dir=tmp_path, camera=camera).from_cache


# --- folders -------------------------------------------------------------------------


def test_mask_folder(tmp_path):
    truth = true_masks("tshape_small")
    for t, mask in enumerate(truth):
        cv2.imwrite(str(tmp_path / f"mask_{t:03d}.png"), mask.astype(np.uint8) * 255)
    for kind in ("auto", "masks"):
        obs = load_observation(tmp_path, kind=kind, fps=30.0)
        assert obs.kind == "masks"
        np.testing.assert_array_equal(obs.coverage_moments, raw_moments(obs.masks))  # a mask is its own coverage
        np.testing.assert_array_equal(obs.masks, truth)
        assert obs.used.all()


def test_image_folder(tmp_path):
    frames = read_frames(DATA / "tshape_small" / "video.mp4", np.arange(12))
    for t, frame in enumerate(frames):
        cv2.imwrite(str(tmp_path / f"frame_{t:03d}.png"), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    from_images = load_observation(tmp_path, fps=30.0)
    from_video = load_observation(DATA / "tshape_small" / "video.mp4")
    assert from_images.kind == "images"
    np.testing.assert_array_equal(from_images.masks, from_video.masks)


# --- undistortion --------------------------------------------------------------------


def test_undistortion(tmp_path):
    truth = true_masks("tshape_small")
    for t, mask in enumerate(truth):
        cv2.imwrite(str(tmp_path / f"{t:03d}.png"), mask.astype(np.uint8) * 255)
    base = json.loads((DATA / "tshape_small" / "camera.json").read_text())
    plain = Camera(**base, dist_coeffs=(0.0, 0.0, 0.0, 0.0))
    obs = load_observation(tmp_path, kind="masks", fps=30.0, camera=plain)
    np.testing.assert_array_equal(obs.masks, truth)
    warped = Camera(**base, dist_coeffs=(-0.4, 0.2, 0.0, 0.0))
    obs = load_observation(tmp_path, kind="masks", fps=30.0, camera=warped)
    assert obs.masks.shape == truth.shape
    assert (obs.masks != truth).any()


# --- contact sheet -------------------------------------------------------------------


def test_contact_sheet(tmp_path, observations):
    obs = observations["tshape_small"]
    path = contact_sheet(obs, None, tmp_path / "sheet" / "masks.png", n=6)
    sheet = cv2.imread(str(path))
    assert sheet is not None and sheet.shape[1] >= 3 * 320  # 96-px frames upscaled
    frames = read_frames(obs.source, obs.frame_indices)
    assert contact_sheet(obs, frames, tmp_path / "given.png").is_file()


# --- bad input -----------------------------------------------------------------------


def test_missing_file(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        load_observation(tmp_path / "nope.mp4")


def test_unreadable_file(tmp_path):
    path = tmp_path / "notes.mp4"
    path.write_text("not a video")
    with pytest.raises(ValueError, match="could not read video"):
        load_observation(path)


def test_video_without_frames(tmp_path):
    path = write_video(tmp_path / "empty.mp4", np.zeros((0, 48, 64, 3), np.uint8))
    with pytest.raises(ValueError, match="no frames"):
        load_observation(path)
    with pytest.raises(ValueError, match="no frames"):
        load_observation(tmp_path, fps=30.0)  # a folder without images


def test_static_video(tmp_path):
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
    path = write_video(tmp_path / "static.mp4", np.repeat(frame[None], 10, axis=0))
    with pytest.raises(ValueError, match="nothing moves"):
        load_observation(path)


def test_size_mismatch(tmp_path):
    camera = Camera.from_file(DATA / "tshape" / "camera.json")  # 640x480
    with pytest.raises(ValueError, match="320x240 but the camera says 640x480"):
        load_observation(DATA / "tshape_small" / "video.mp4", camera=camera)
    for t, mask in enumerate(true_masks("tshape_small")):
        cv2.imwrite(str(tmp_path / f"{t:03d}.png"), mask.astype(np.uint8) * 255)
    with pytest.raises(ValueError, match="but the camera says"):
        load_observation(tmp_path, fps=30.0, camera=camera)


def test_principal_point_outside_image(tmp_path):
    base = json.loads((DATA / "tshape_small" / "camera.json").read_text())
    path = tmp_path / "camera.json"
    path.write_text(json.dumps({**base, "cx": 900.0}))
    with pytest.raises(ValueError, match="principal point outside the image"):
        load_observation(DATA / "tshape_small" / "video.mp4", camera=path)


@pytest.mark.parametrize("fps", [0.0, -30.0, float("nan")])
def test_bad_fps(fps):
    with pytest.raises(ValueError, match="fps must be positive"):
        load_observation(DATA / "tshape_small" / "video.mp4", fps=fps)


def test_folder_needs_fps(tmp_path):
    cv2.imwrite(str(tmp_path / "0.png"), np.zeros((8, 8), np.uint8))
    with pytest.raises(ValueError, match="fps must be given"):
        load_observation(tmp_path)


@pytest.mark.parametrize("start, stop, match", [
    (12, None, "start = 12 is out of range"),
    (0, 13, "stop = 13 is out of range"),
    (-1, None, "start must be a non-negative integer"),
    (5, 5, "stop must be an integer > start"),
])
def test_bad_range(start, stop, match):
    with pytest.raises(ValueError, match=match):
        load_observation(DATA / "tshape_small" / "video.mp4", start=start, stop=stop)


def test_bad_method_and_kind():
    with pytest.raises(ValueError, match='Invalid method "gmm"'):
        load_observation(DATA / "tshape_small" / "video.mp4", method="gmm")
    with pytest.raises(ValueError, match='Invalid kind "film"'):
        load_observation(DATA / "tshape_small" / "video.mp4", kind="film")


def test_frame_flags(tmp_path):
    masks = np.zeros((14, 40, 70), bool)
    for t in range(14):
        masks[t, 10:16, 5 + 3 * t:11 + 3 * t] = True  # a 6x6 square moving right
    masks[3] = False  # no object
    masks[6, 0:6] = masks[6, 10:16]  # touches the top border
    masks[9, 8:22, 30:50] = True  # area jumps
    masks[12, 30:36, 10:16] = True  # a second component as large as the first
    for t, mask in enumerate(masks):
        cv2.imwrite(str(tmp_path / f"{t:02d}.png"), mask.astype(np.uint8) * 255)
    obs = load_observation(tmp_path, fps=10.0)
    assert [t for t in range(14) if not obs.used[t]] == [3, 6, 9, 12]
    assert obs.reasons[3] == "no object" and obs.reasons[6] == "touches the image border"
    assert obs.reasons[9].startswith("area jumps") and obs.reasons[12] == "several large components"
    assert np.isnan(obs.boxes[3]).all()
    np.testing.assert_array_equal(obs.boxes[0], [5, 10, 10, 15])


@pytest.mark.parametrize("field", ["noise_sigmas", "alpha_smoothing", "shading_radius", "chroma_weight"])
def test_negative_settings_are_refused(field):
    with pytest.raises(ValueError, match=f"{field} must be >= 0, got -1.0"):
        SegmentationSettings(**{field: -1.0})


def test_undistortion_keeps_the_outline_where_it_was():
    """Discs drawn through a barrel lens (8x8 samples per pixel) and undistorted come back where
    they were drawn: centroid within 0.15 px RMS (nearest-neighbour resampling: 0.19) and area
    within 0.5 % on average."""
    width, height, radius = 320, 240, 12.0
    camera = Camera(fx=300.0, fy=300.0, cx=159.5, cy=119.5, width=width, height=height,
                    dist_coeffs=(-0.3, 0.1, 0.0, 0.0))
    sub = 8
    v, u = np.mgrid[0:height * sub, 0:width * sub].astype(np.float64)
    samples = np.stack([(u + 0.5) / sub - 0.5, (v + 0.5) / sub - 0.5], -1).reshape(-1, 1, 2)
    undistorted = cv2.undistortPoints(samples, camera.K, np.asarray(camera.dist_coeffs), P=camera.K)
    undistorted = undistorted.reshape(height, sub, width, sub, 2)
    rng = np.random.default_rng(0)
    centres = np.stack([rng.uniform(40, width - 40, 40), rng.uniform(40, height - 40, 40)], -1)
    drawn = np.stack([(((undistorted - c) ** 2).sum(-1) <= radius**2).mean((1, 3)) >= 0.5 for c in centres])
    masks = _undistort(drawn, camera)
    errors, areas = [], []
    for mask, centre in zip(masks, centres):
        ys, xs = np.nonzero(mask)
        errors.append((xs.mean() - centre[0], ys.mean() - centre[1]))
        areas.append(mask.sum() / (np.pi * radius**2) - 1.0)
    assert np.sqrt((np.asarray(errors) ** 2).sum(1).mean()) < 0.15
    assert abs(np.mean(areas)) < 0.005


def test_soft_coverage_moments_are_the_blurred_frames_own():
    """The segmentation keeps the raw moments of each frame's soft coverage (``coverage_moments``).
    On a disc blurred by 10 px of travel, with one albedo pass, they are those of the exact
    coverage (measured: area -1.0 %, variance along the motion -3.8 %, across -0.1 %), while
    the mask's 0.5 contour is narrower along the motion (variance -23 %): the exposure's average
    moments are what the coverage shows, not the mask."""
    frames, covers = _blurred_disc_frames()
    # the band of 4 steps: this 100 x 200 clip's blur is 10 px, as at 640 x 480 ("auto" would count 1)
    out = _segment(frames, SegmentationSettings(albedo_passes=1, coverage_near_px=4))
    inner = slice(2, -2)  # the first and last frames' background median is the weakest
    exact = central_moments(torch.as_tensor(raw_moments(covers[inner])))
    soft = central_moments(torch.as_tensor(out["coverage_moments"][inner]))
    mask = central_moments(torch.as_tensor(raw_moments(out["masks"][inner])))

    def relative(moments, index):
        value = moments[0] if index is None else moments[2][:, index, index]
        reference = exact[0] if index is None else exact[2][:, index, index]
        return float(((value - reference) / reference).mean())

    assert abs(relative(soft, None)) < 0.02 and abs(relative(soft, 0)) < 0.06 and abs(relative(soft, 1)) < 0.01
    assert relative(mask, 0) < -0.15
    assert float((soft[1] - exact[1]).abs().max()) < 0.02  # px


def test_coverage_moments_are_taken_undistorted_through_a_lens():
    """With a distorted camera the soft coverage is resampled through the undistortion before its
    moments are taken: the blurred disc's frames imaged through a barrel lens (k1 -0.3, the disc
    up to 60 px off the centre) give the undistorted exact coverage's centroid within 0.08 px
    (measured: at most 0.045) and its area within 2 % (at most -1.1 %), where the moments as
    imaged are off by up to 3.2 px."""
    frames, covers = _blurred_disc_frames()
    height, width = covers.shape[1:]
    camera = Camera(fx=150.0, fy=150.0, cx=(width - 1) / 2, cy=(height - 1) / 2, width=width, height=height,
                    dist_coeffs=(-0.3, 0.0, 0.0, 0.0))
    # imaged through the lens: each distorted pixel shows the scene where the lens maps it from
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    points = np.stack([u, v], -1).reshape(-1, 1, 2)
    source = cv2.undistortPoints(points, camera.K, np.asarray(camera.dist_coeffs), P=camera.K).reshape(height, width, 2)
    maps = source[..., 0].astype(np.float32), source[..., 1].astype(np.float32)
    imaged = np.stack([cv2.remap(f, *maps, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
                       for f in frames])
    settings = SegmentationSettings(albedo_passes=1, coverage_near_px=4)  # the blur of a 640 x 480 clip
    out = _segment(imaged, settings, _undistort_maps(camera))
    as_imaged = _segment(imaged, settings)
    inner = slice(2, -2)  # the first and last frames' background median is the weakest
    exact = central_moments(torch.as_tensor(raw_moments(covers[inner])))
    soft = central_moments(torch.as_tensor(out["coverage_moments"][inner]))
    raw = central_moments(torch.as_tensor(as_imaged["coverage_moments"][inner]))
    assert float((soft[1] - exact[1]).norm(dim=-1).max()) < 0.08  # px
    assert float(((soft[0] - exact[0]) / exact[0]).abs().max()) < 0.02
    assert float((raw[1] - exact[1]).norm(dim=-1).max()) > 1.0


def test_undistorted_coverage_of_thin_bars_keeps_no_radial_residual():
    """Thin bars (2.5 px by 30 px, at random places and angles) imaged through a barrel lens as
    exact coverage (8x8 samples per pixel) and undistorted as the segmentation undistorts a
    coverage: their centroids come back where the pinhole puts them, with no radial term left.
    Fitted as an offset plus ``d k1 f x_n r_n^2`` (the shift a change of k1 makes), ``d k1`` is
    below 0.0005 (measured: 0.00005; undistorted through a lens 9 % more barrel it reads +0.0072),
    where a T-handle through this lens on video reads -0.004 to -0.013
    (experiments/discover/HISTORY.md, *Twenty-seventh session*), and every centroid is within
    0.1 px (measured: 0.025)."""
    width, height, sub, length, thickness = 640, 480, 8, 30.0, 2.5
    camera = Camera(fx=659.4, fy=659.4, cx=319.5, cy=239.5, width=width, height=height,
                    dist_coeffs=(-0.08, 0.01, 0.0, 0.0))
    K, dist = camera.K, np.asarray(camera.dist_coeffs)
    maps = _undistort_maps(camera)
    rng = np.random.default_rng(1)
    seen, true = [], []
    for _ in range(30):
        centre, angle = rng.uniform((60, 60), (width - 60, height - 60)), rng.uniform(0, np.pi)
        at = cv2.projectPoints(np.array([[*(centre - K[:2, 2]) / K[0, 0], 1.0]]), np.zeros(3), np.zeros(3), K, dist)[0]
        x0, y0 = (at[0, 0] - 30).astype(int)
        v, u = np.mgrid[0:60 * sub, 0:60 * sub].astype(np.float64)
        points = np.stack([x0 + (u + 0.5) / sub - 0.5, y0 + (v + 0.5) / sub - 0.5], -1).reshape(-1, 1, 2)
        offset = cv2.undistortPoints(points, K, dist, P=K).reshape(60 * sub, 60 * sub, 2) - centre
        along = offset[..., 0] * np.cos(angle) + offset[..., 1] * np.sin(angle)
        across = -offset[..., 0] * np.sin(angle) + offset[..., 1] * np.cos(angle)
        cover = np.zeros((height, width), np.float32)
        cover[y0:y0 + 60, x0:x0 + 60] = ((np.abs(along) <= length / 2) & (np.abs(across) <= thickness / 2)
                                         ).reshape(60, sub, 60, sub).mean((1, 3))
        moments = raw_moments(cv2.remap(cover, *maps, interpolation=cv2.INTER_LINEAR)[None])[0]
        seen.append(moments[1:3] / moments[0])
        true.append(centre)
    seen, true = np.array(seen), np.array(true)
    normal = (true - K[:2, 2]) / K[0, 0]
    design = np.zeros((2 * len(true), 3))
    design[0::2, 0], design[1::2, 1] = 1.0, 1.0
    design[:, 2] = (K[0, 0] * normal * (normal**2).sum(1, keepdims=True)).ravel()
    (_, _, d_k1), *_ = np.linalg.lstsq(design, (seen - true).ravel(), rcond=None)
    assert abs(d_k1) < 5e-4
    assert np.abs(seen - true).max() < 0.1  # px

def test_clipped_coverage_turns_background_noise_into_mass():
    """``coverage_clip``: the coverage's noise is zero-mean, so clipping it to [0, 1] makes every
    background pixel of the band count for mass, and the moments grow with the band (the blurred
    disc with noise of sigma 3 grey levels: m00 +1.3 % from a band of 6 to one of 12, measured).
    Unclipped they do not grow (measured -0.9 %: on this short clip the median background leans
    toward the disc that crosses it, so the background reads a little below 0)."""
    frames, covers = _blurred_disc_frames()
    noisy = np.clip(np.round(frames + np.random.default_rng(0).normal(0.0, 3.0, frames.shape)), 0, 255)
    inner = slice(2, -2)
    exact = raw_moments(covers[inner])[:, 0].mean()

    def area(band, clip):
        out = _segment(noisy.astype(np.uint8), SegmentationSettings(albedo_passes=1, coverage_near_px=band,
                                                                   coverage_clip=clip))
        return out["coverage_moments"][inner, 0].mean() / exact

    assert area(12, True) - area(6, True) > 0.008
    assert area(12, False) - area(6, False) < 0.0


def test_coverage_band_sets_how_much_of_the_blurred_ramp_counts():
    """``coverage_near_px``: the coverage's moments count the pixels within that many steps of the
    mask. On the disc blurred by 10 px of travel the ramp reaches about 5 px past the mask's edge,
    so the default band of 4 reads the variance along the motion short (measured -3.8 %), a band
    of 1 much shorter (-25 %), and one of 6 takes all of it (-0.1 %)."""
    frames, covers = _blurred_disc_frames()
    inner = slice(2, -2)
    exact = central_moments(torch.as_tensor(raw_moments(covers[inner])))[2][:, 0, 0]

    def along(band):
        out = _segment(frames, SegmentationSettings(albedo_passes=1, coverage_near_px=band))
        return float(((central_moments(torch.as_tensor(out["coverage_moments"][inner]))[2][:, 0, 0] - exact)
                      / exact).mean())

    assert along(1) < -0.15
    assert -0.06 < along(4) < -0.02
    assert abs(along(6)) < 0.01
    with pytest.raises(ValueError, match="coverage_near_px"):
        SegmentationSettings(coverage_near_px=0)


def test_auto_band_counts_the_640_by_480_cameras_steps_in_this_cameras_pixels():
    """``coverage_near_px="auto"``: ``round(4 sqrt(H W / (640 480)))`` steps, 4 at 640 x 480 (so
    the concealed sets' runs are unchanged by it), 8 through twice the pixels; ``_segment`` counts
    that band (the 100 x 200 disc: 1 step, the ramp read as short as with a fixed band of 1)."""
    auto = SegmentationSettings(coverage_near_px="auto")
    sizes = ((480, 640), (960, 1280), (720, 1280), (1080, 1920), (100, 200))
    assert [auto.band_steps(h, w) for h, w in sizes] == [4, 8, 7, 10, 1]
    assert SegmentationSettings(coverage_near_px=6).band_steps(960, 1280) == 6
    frames, _ = _blurred_disc_frames()

    def moments(band):
        return _segment(frames, SegmentationSettings(albedo_passes=1, coverage_near_px=band))["coverage_moments"]

    np.testing.assert_array_equal(moments("auto"), moments(1))
    assert not np.allclose(moments("auto"), moments(4))
    for bad in ("8", True, 2.5, "Auto"):
        with pytest.raises(ValueError, match='coverage_near_px must be a whole number of steps >= 1 or "auto"'):
            SegmentationSettings(coverage_near_px=bad)


def test_motion_band_keeps_the_ramp_along_the_motion_only():
    """``coverage_band="motion"``: the band of ``coverage_near_px`` steps swept half the frame's
    travel along the motion. On the disc blurred by 10 px of travel (10 px a frame) the band of 4
    reads the variance along the motion short (-3.8 %, above); swept, it takes the whole ramp
    (measured -0.1 %) and counts no more pixels across the motion than the band of 4 steps."""
    frames, covers = _blurred_disc_frames()
    inner = slice(2, -2)
    exact = central_moments(torch.as_tensor(raw_moments(covers[inner])))[2][:, 0, 0]
    out = _segment(frames, SegmentationSettings(albedo_passes=1, coverage_band="motion"))
    along = float(((central_moments(torch.as_tensor(out["coverage_moments"][inner]))[2][:, 0, 0] - exact)
                   / exact).mean())
    assert abs(along) < 0.01

    mask = out["masks"][5]
    steps = ndimage.binary_dilation(mask, iterations=4)
    swept = motion_band(mask, 4, np.array([10.0, 0.0]))
    assert (swept >= steps).all()
    assert (swept.any(1) == steps.any(1)).all()  # rows: no wider across the motion
    assert swept.any(0).sum() == steps.any(0).sum() + 10  # columns: half the travel either way
    with pytest.raises(ValueError, match="coverage_band"):
        SegmentationSettings(coverage_band="wide")


@pytest.mark.parametrize("fit, area_excess, spread_px2", [("constant", (0.03, 0.06), (0.4, 0.8)),
                                                         ("linear", (0.0, 0.03), (-0.15, 0.15))])
def test_local_linear_shading_reads_a_shaded_limb(fit, area_excess, spread_px2):
    """``shading_fit``: a sharp disc shaded like a lit ball (a third of its centre's brightness at
    the edge). The local-constant shading borrows the brighter inside at the limb, so the coverage
    reads too large and wider in every direction (measured: area +4.5 %, variance +0.60 px²); the
    local-linear one takes most of that away (+2.6 %, +0.05 px²)."""
    frames, covers = _blurred_disc_frames(blur_px=0.0, limb=0.3)
    inner = slice(2, -2)
    exact = central_moments(torch.as_tensor(raw_moments(covers[inner])))
    out = _segment(frames, SegmentationSettings(albedo_passes=1, coverage_clip=False, shading_fit=fit))
    seen = central_moments(torch.as_tensor(out["coverage_moments"][inner]))
    area = float((seen[0] / exact[0]).mean()) - 1
    spread = float(torch.diagonal(seen[2] - exact[2], dim1=-2, dim2=-1).mean())
    assert area_excess[0] < area < area_excess[1]
    assert spread_px2[0] < spread < spread_px2[1]
    with pytest.raises(ValueError, match="shading_fit"):
        SegmentationSettings(shading_fit="quadratic")


# --- a camera held in the hand -------------------------------------------------------


def _shaken_scene(maps: np.ndarray, height: int = 120, width: int = 160, seed: int = 3) -> np.ndarray:
    """(T, H, W, 3) uint8 BGR frames of a smooth random texture with a dark disc (radius 8 px)
    crossing it from left to right, each whole frame then moved by its map of (T, 3, 3) ``maps``
    (a still pixel to the frame's; Lanczos) from a scene 16 px wider on every side, so a moved
    frame's border shows more of the scene: what a still camera sees, shaken. Identities give
    the still clip."""
    margin = 16
    rng = np.random.default_rng(seed)
    big = (height + 2 * margin, width + 2 * margin)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, big + (3,)).astype(np.float32), (0, 0), 2.0)
    texture = 128 + 2.5 * (texture - texture.mean())
    count, samples = len(maps), 4
    v, u = (np.mgrid[0:big[0] * samples, 0:big[1] * samples] + 0.5) / samples - 0.5 - margin
    into_scene = np.array([[1.0, 0.0, -margin], [0.0, 1.0, -margin], [0.0, 0.0, 1.0]])
    frames = []
    for t, warp in enumerate(maps):
        cx = 30.0 + 100.0 * t / max(count - 1, 1)
        cover = ((u - cx) ** 2 + (v - 60.0) ** 2 <= 8.0 ** 2).reshape(big[0], samples, big[1], samples).mean((1, 3))
        frame = texture * (1 - cover[..., None]) + np.array([40.0, 60.0, 200.0]) * cover[..., None]
        frame = cv2.warpPerspective(frame.astype(np.float32), warp @ into_scene, (width, height),
                                    flags=cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_REPLICATE)
        frames.append(np.clip(np.rint(frame), 0, 255).astype(np.uint8))
    return np.stack(frames)


def _shake(count: int = 20, amplitude: float = 1.5, seed: int = 1, turn: float = 0.0) -> np.ndarray:
    """(count, 3) a smooth random shake ``(dx, dy, turn)``: ``amplitude`` px RMS per axis and
    ``turn`` degrees RMS about the image centre, about its median."""
    noise = ndimage.gaussian_filter1d(np.random.default_rng(seed).normal(size=(count, 3)), 2.0, axis=0)
    motion = np.array([amplitude, amplitude, turn]) * noise / noise.std(0)
    return motion - np.median(motion, 0)


def _rigid(rows: np.ndarray, size: tuple[int, int] = (120, 160)) -> np.ndarray:
    """(T, 3, 3) the maps of (T, 3) rows ``(dx, dy, turn)`` (``video._motion_matrices``)."""
    from torchfit.video import _motion_matrices

    return _motion_matrices(rows, size)


def _turned_camera(degrees: float, count: int = 20, seed: int = 4, focal: float = 150.0,
                   size: tuple[int, int] = (120, 160)) -> np.ndarray:
    """(count, 3, 3) the maps ``K R K^-1`` of a camera (focal length ``focal`` px, principal point
    at the centre of an image of ``size``) panned, tilted and rolled by a smooth random
    ``degrees`` RMS each (:func:`_shake`'s path): what a far background does when the camera
    held in the hand turns about any axis."""
    height, width = size
    k = np.array([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]])
    angles = np.radians(_shake(count, degrees, seed, degrees))
    maps = []
    for pan, tilt, roll in angles:
        rotation = cv2.Rodrigues(np.array([tilt, pan, roll]))[0]
        h = k @ rotation @ np.linalg.inv(k)
        maps.append(h / h[2, 2])
    return np.stack(maps)


def _map_error(found: np.ndarray, truth: np.ndarray, size: tuple[int, int] = (120, 160)) -> np.ndarray:
    """(T, 5) how far (px) (T, 3, 3) maps ``found`` put a still frame's four corners and its centre
    from where ``truth`` puts them, each about its median over the frames."""
    from torchfit.video import _corners, _mapped

    points = np.vstack([_corners(size), [[(size[1] - 1) / 2, (size[0] - 1) / 2, 1.0]]])
    apart = _mapped(found, points) - _mapped(truth, points)
    return np.linalg.norm(apart - np.median(apart, axis=0), axis=2)


def test_motion_rows_and_matrices_are_inverse_and_a_turn_moves_the_corners_most():
    """``_motion_rows`` reads back what ``_motion_matrices`` made; a pure turn by ``a`` about the
    centre moves a corner, ``r`` from it, by ``2 r sin(a / 2)`` and the centre not at all; a
    shift moves every pixel by its length. Of a homography, ``_motion_rows`` gives where the
    centre goes and the turn of the map's Jacobian there (against central differences)."""
    from torchfit.video import _largest_move, _mapped, _motion_matrices, _motion_rows

    size = (120, 160)
    motion = np.array([[0.3, -1.2, 0.7], [-2.0, 0.5, -1.5], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(_motion_rows(_motion_matrices(motion, size), size), motion, atol=1e-12)
    radius = np.hypot(159 / 2, 119 / 2)
    assert _largest_move(_rigid(np.array([[0.0, 0.0, 0.5]])), size) == pytest.approx(
        2 * radius * np.sin(np.radians(0.25)))
    assert _largest_move(_rigid(np.array([[3.0, 4.0, 0.0]])), size) == pytest.approx(5.0)
    centre = _motion_matrices(np.array([[0.0, 0.0, 2.0]]), size)[0] @ np.array([159 / 2, 119 / 2, 1.0])
    np.testing.assert_allclose(centre[:2], [159 / 2, 119 / 2], atol=1e-12)
    maps = _turned_camera(2.0, count=3)
    rows = _motion_rows(maps, size)
    c, h = np.array([159 / 2, 119 / 2, 1.0]), 1e-4
    np.testing.assert_allclose(rows[:, :2], _mapped(maps, c[None])[:, 0] - c[:2], atol=1e-12)
    dx = (_mapped(maps, (c + [h, 0, 0])[None]) - _mapped(maps, (c - [h, 0, 0])[None]))[:, 0] / (2 * h)
    dy = (_mapped(maps, (c + [0, h, 0])[None]) - _mapped(maps, (c - [0, h, 0])[None]))[:, 0] / (2 * h)
    turn = np.degrees(np.arctan2(dy[:, 0] - dx[:, 1], dx[:, 0] + dy[:, 1]))
    np.testing.assert_allclose(rows[:, 2], turn, atol=1e-7)
    assert np.abs(rows[:, 2]).max() > 0.5  # the camera's roll turns the picture


def test_turn_map_is_the_turned_cameras_homography_and_its_slopes_match_finite_differences():
    """``_turn_map`` of a pan, a tilt or a roll alone is ``shake.py``'s ``K R K^-1`` for it, a
    shift moves the picture after the turn, and the points' slopes (``_point_slopes``, through
    ``_turn_map_derivatives``) match central differences of the mapped points in float64."""
    from torchfit.video import _mapped, _point_slopes, _turn_map, _turn_map_derivatives

    k = np.array([[659.0, 0.0, 319.5], [0.0, 655.0, 239.5], [0.0, 0.0, 1.0]])
    for axis in range(3):
        rotation = np.zeros(3)
        rotation[axis] = np.radians(0.7)
        expected = k @ cv2.Rodrigues(rotation)[0] @ np.linalg.inv(k)
        np.testing.assert_allclose(_turn_map(np.r_[rotation, 0.0, 0.0], k), expected / expected[2, 2], atol=1e-12)
    pan = np.array([0.0, np.radians(0.7), 0.0])
    shifted = np.array([[1, 0, 2.5], [0, 1, -1.0], [0, 0, 1]]) @ _turn_map(np.r_[pan, 0.0, 0.0], k)
    np.testing.assert_allclose(_turn_map(np.r_[pan, 2.5, -1.0], k), shifted / shifted[2, 2], atol=1e-12)
    params = np.array([0.004, -0.006, 0.01, 1.5, -2.0])
    points = np.array([[0.0, 0.0, 1.0], [639.0, 0.0, 1.0], [300.0, 200.0, 1.0], [639.0, 479.0, 1.0]])
    slopes = _point_slopes(points, _turn_map(params, k), _turn_map_derivatives(params, k))
    for i, step in enumerate([1e-6, 1e-6, 1e-6, 1e-4, 1e-4]):
        ahead, back = params.copy(), params.copy()
        ahead[i] += step
        back[i] -= step
        numeric = (_mapped(_turn_map(ahead, k)[None], points) - _mapped(_turn_map(back, k)[None], points))[0]
        numeric /= 2 * step
        np.testing.assert_allclose(slopes[:, :, i], numeric, rtol=1e-5, atol=1e-6)
    assert np.abs(slopes[:, :, 1]).max() > 600  # a pan moves a pixel about f per radian


def test_unseen_border_is_marked_and_filled_with_the_background():
    """A frame moved back by a shift of 3 px to the right did not see its last 3 columns, and
    Lanczos drew the next 4 from them (``unseen_pixels``); a frame not moved saw everything.
    Those pixels take the median of the frames that saw them, the rest stay as they were."""
    from torchfit.video import LANCZOS_REACH_PX, _background_where_unseen, unseen_pixels

    motion = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    unseen = unseen_pixels(_rigid(motion, (20, 30)), (20, 30))
    assert not unseen[0].any() and not unseen[2].any()
    np.testing.assert_array_equal(np.flatnonzero(unseen[1].any(0)), np.arange(30 - 3 - LANCZOS_REACH_PX, 30))
    assert unseen[1].all(0)[-1]
    frames = np.stack([np.full((20, 30, 3), v, np.uint8) for v in (10, 200, 30, 20)])
    filled = _background_where_unseen(frames, unseen)
    np.testing.assert_array_equal(filled[1][~unseen[1]], 200)
    np.testing.assert_array_equal(filled[1][unseen[1]], 20)  # the median of 10, 30, 20
    np.testing.assert_array_equal(filled[[0, 2, 3]], frames[[0, 2, 3]])


def test_camera_motion_reads_a_known_shake():
    """``camera_motion`` reads a smooth shake of 1.5 px RMS per axis (up to 3.4 px), with the
    moving disc left out, to a few hundredths of a pixel at every corner and no turn (under a
    hundredth of a degree); a turn of
    0.5 deg RMS about the line of sight to about a hundredth of a degree; a camera turned 1 deg
    RMS about every axis (whose shift and turn at the centre, all a rigid registration takes,
    put the corners 1.6 px RMS off) to under a tenth of a pixel at the worst corner (worst
    where the disc hides the background beside it) and the centre to a hundredth, given the
    camera's intrinsics; a still clip as still."""
    from torchfit.video import _motion_rows, camera_motion

    size = (120, 160)
    shift = _rigid(np.column_stack([_shake()[:, :2], np.zeros(20)]))
    found = camera_motion(_shaken_scene(shift)).maps
    error = _map_error(found, shift)
    assert np.sqrt((error.max(1) ** 2).mean()) < 0.04 and error.max() < 0.1
    assert np.abs(_motion_rows(found, size)[:, 2]).max() < 0.01
    turned = _shake(amplitude=1.0, turn=0.5, seed=2)
    found = camera_motion(_shaken_scene(_rigid(turned))).maps
    assert np.sqrt((_map_error(found, _rigid(turned)).max(1) ** 2).mean()) < 0.04
    assert np.abs(_motion_rows(found, size)[:, 2] - turned[:, 2]).max() < 0.02
    camera = _turned_camera(1.0)
    rigid_part = _rigid(_motion_rows(camera, size))  # the first-order map the rigid registration took
    assert np.sqrt((_map_error(rigid_part, camera).max(1) ** 2).mean()) > 1.0
    found = camera_motion(_shaken_scene(camera), Camera(150.0, 150.0, 79.5, 59.5, 160, 120)).maps
    error = _map_error(found, camera)
    assert np.sqrt((error.max(1) ** 2).mean()) < 0.1 and np.sqrt((error[:, 4] ** 2).mean()) < 0.02
    still = camera_motion(_shaken_scene(np.tile(np.eye(3), (20, 1, 1))))
    assert _map_error(still.maps, np.tile(np.eye(3), (20, 1, 1))).max() < 0.03
    assert still.registered.all() and still.correlation.min() > 0.99


def test_camera_motion_standard_errors_match_the_spread_of_its_maps():
    """A still textured scene seen through independent pixel noise of 2 grey levels: the maps'
    corners scatter about the identity as ``CameraMotion.sigma_px`` says before its factor for
    correlated pixels (their RMS over the frames and corners within 0.6-1.6 times the RMS
    standard error), and four times the noise gives about four times both; the chi-squared per
    parameter is then about 1."""
    from torchfit.video import MOTION_SIGMA_FACTOR, _corners, _mapped, camera_motion

    still = _shaken_scene(np.tile(np.eye(3), (20, 1, 1))).astype(np.float64)
    spreads = []
    for noise in (2.0, 8.0):
        rng = np.random.default_rng(11)
        frames = np.clip(np.rint(still + rng.normal(0, noise, still.shape)), 0, 255).astype(np.uint8)
        found = camera_motion(frames)
        corners = _corners((120, 160))
        error = np.linalg.norm(_mapped(found.maps, corners) - corners[None, :, :2], axis=2)  # (T, 4)
        ratio = np.sqrt((error ** 2).mean()) / np.sqrt((found.sigma_px ** 2).mean()) * MOTION_SIGMA_FACTOR
        assert 0.6 < ratio < 1.6, (noise, ratio)
        assert 0.4 < found.chi2.mean() / found.dof * MOTION_SIGMA_FACTOR ** 2 < 2.5
        spreads.append(np.sqrt((found.sigma_px ** 2).mean()))
    assert 2.5 < spreads[1] / spreads[0] < 6


def _plain_scene(maps: np.ndarray, height: int = 120, width: int = 160, seed: int = 3) -> np.ndarray:
    """(T, H, W, 3) uint8 frames of a plain wall over a darker floor (a horizon at 60 % of the
    height), shaded by faint broad blotches (2 grey levels RMS, 6 px across) and grained by
    noise of 1 grey level a frame, with a large textured disc (radius 18 px) crossing it, each
    frame moved by its map of (T, 3, 3) ``maps`` as :func:`_shaken_scene` does: little besides
    the object for a registration to hold on to."""
    margin = 16
    rng = np.random.default_rng(seed)
    big = (height + 2 * margin, width + 2 * margin)
    v, u = np.mgrid[0:big[0], 0:big[1]]
    wall = cv2.GaussianBlur((np.where(v < big[0] * 0.6, 150.0, 110.0) + 0.05 * u).astype(np.float32), (0, 0), 1.0)
    blotches = cv2.GaussianBlur(rng.normal(0, 1, big).astype(np.float32), (0, 0), 6.0)
    wall = wall + 2.0 * blotches / blotches.std()
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (40, 40)).astype(np.float32), (0, 0), 1.5)
    texture = 100 + 3 * (texture - texture.mean())
    disc = ((np.mgrid[0:40, 0:40] - 19.5) ** 2).sum(0) <= 18 ** 2
    into_scene = np.array([[1.0, 0.0, -margin], [0.0, 1.0, -margin], [0.0, 0.0, 1.0]])
    frames = []
    for t, warp in enumerate(maps):
        scene = wall.copy()
        x0 = int(margin + 30 + 100 * t / (len(maps) - 1)) - 20
        y0 = int(margin + 40 + 10 * np.sin(t / 5)) - 20
        scene[y0:y0 + 40, x0:x0 + 40][disc] = texture[disc]
        frame = cv2.warpPerspective(scene, warp @ into_scene, (width, height), flags=cv2.INTER_LANCZOS4,
                                    borderMode=cv2.BORDER_REPLICATE) + rng.normal(0, 1.0, (height, width))
        frames.append(np.repeat(np.clip(np.rint(frame), 0, 255).astype(np.uint8)[..., None], 3, 2))
    return np.stack(frames)


def test_passes_run_until_the_maps_settle_against_a_plain_wall():
    """Against a plain wall the first pass, which registers with the object in, is dragged by the
    object's move, and a second with the object masked does not pull the map back: held to two
    passes the worst corner of a shake of 1.5 px RMS lands 0.45 px RMS off; passes until the
    maps settle (``MOTION_SETTLED_PX``) bring it under a tenth."""
    from torchfit.video import camera_motion

    shake = _rigid(np.column_stack([_shake()[:, :2], np.zeros(20)]))
    frames = _plain_scene(shake)
    held = camera_motion(frames, max_passes=2)
    settled = camera_motion(frames)
    assert held.passes == 2 and settled.passes > 2
    assert np.sqrt((_map_error(held.maps, shake)[:, :4].max(1) ** 2).mean()) > 0.3
    assert np.sqrt((_map_error(settled.maps, shake)[:, :4].max(1) ** 2).mean()) < 0.1


def test_a_background_without_texture_does_not_register():
    """Against a flat background a registration has only noise and the moving object to go by
    (it once moved a corner thousands of pixels); a frame whose background does not correlate
    with the clip's (``MOTION_MIN_CORRELATION``) keeps its map, so the clip reads as still, and
    says that it did not register."""
    from torchfit.video import MOTION_MIN_CORRELATION, STILL_PX, _largest_move, camera_motion

    rng = np.random.default_rng(5)
    frames = np.full((10, 120, 160, 3), (170, 180, 200), np.float64)
    v, u = np.mgrid[0:120, 0:160]
    for t, frame in enumerate(frames):
        disc = (u - 30 - 10 * t) ** 2 + (v - 60) ** 2 <= 12 ** 2
        frame[disc] = (40, 40, 40)
    frames = np.clip(np.rint(frames + rng.normal(0, 1.0, frames.shape)), 0, 255).astype(np.uint8)
    found = camera_motion(frames)
    assert _largest_move(found.maps, (120, 160)) < STILL_PX
    assert not found.registered.any()
    np.testing.assert_array_equal(found.registered, found.correlation >= MOTION_MIN_CORRELATION)


def test_a_shaken_clip_is_segmented_as_the_still_one(tmp_path):
    """A clip shaken by 1.5 px RMS and turned 0.5 deg RMS (stored losslessly) is moved back before it is segmented
    (``stabilise="auto"``, past ``STILL_PX``): its masks' centroids are the still clip's to a tenth
    of a pixel, the frames as segmented (``observed_frames``) are the still ones, and the report's
    sentence says so. With ``stabilise=False`` the offsets are measured alike, the centroids
    miss the still clip's by more than a pixel RMS, and the sentence warns that the model takes a
    still camera."""
    from torchfit.video import STILL_PX, _largest_move, camera_motion_note, observed_frames

    offsets = _shake(turn=0.5)
    folders = {}
    for name, shift in (("still", np.zeros_like(offsets)), ("shaken", offsets)):
        folders[name] = tmp_path / name
        folders[name].mkdir()
        for t, frame in enumerate(_shaken_scene(_rigid(shift))):
            cv2.imwrite(str(folders[name] / f"{t:03d}.png"), frame)
    still = load_observation(folders["still"], fps=60.0)
    moved = load_observation(folders["shaken"], fps=60.0)
    kept = load_observation(folders["shaken"], fps=60.0, settings=SegmentationSettings(stabilise=False))
    assert not still.stabilised and still.camera_moved_px < STILL_PX and camera_motion_note(still) == ""
    assert moved.stabilised and not kept.stabilised
    np.testing.assert_allclose(moved.camera_motion, kept.camera_motion)
    assert moved.camera_moved_px == pytest.approx(_largest_move(_rigid(offsets), (120, 160)), abs=0.1)

    def centroids(observation):
        m = raw_moments(observation.masks.astype(np.float64))
        return m[:, 1:3] / m[:, :1]

    assert np.abs(centroids(moved) - centroids(still)).max() < 0.1
    # not moved back: the shake as filmed, and a background median blurred by it
    assert np.sqrt(((centroids(kept) - centroids(still)) ** 2).sum(1).mean()) > 1.0
    inner = (slice(None), slice(8, -8), slice(8, -8))
    assert np.abs(observed_frames(moved).astype(float) - observed_frames(still).astype(float))[inner].mean() < 1.0
    assert "moved back before they were segmented" in camera_motion_note(moved)
    assert "not moved back" in camera_motion_note(kept) and "still camera" in camera_motion_note(kept)


def test_frames_whose_background_does_not_register_are_said_and_left_out_of_a_moved_back_clip(tmp_path,
                                                                                              monkeypatch):
    """A shaken clip (1.5 px RMS) whose registration refuses frames 8 and 9 (their background
    under ``MOTION_MIN_CORRELATION``, as a flat wall's is: the test above) says so
    (``camera_registered``, ``camera_correlation``, ``discover.json``'s fields, the report's
    note naming them) and, the clip being moved back, leaves them out of the fit ("camera move
    not measured"); every other frame is used. Not moved back (``stabilise=False``), they
    stay in, and the note warns that a move there would not be seen."""
    from torchfit import video
    from torchfit.video import camera_motion_fields, camera_motion_note

    shake = _rigid(_shake())
    for t, frame in enumerate(_shaken_scene(shake)):
        cv2.imwrite(str(tmp_path / f"{t:03d}.png"), frame)
    lost = np.isin(np.arange(20), [8, 9])
    correlation = np.where(lost, 0.5, 0.999)
    correlation[9] = np.nan  # nothing left to compare
    registered = video.camera_motion(_shaken_scene(shake))

    def refusing(frames, camera=None):
        maps = registered.maps.copy()
        maps[lost] = np.eye(3)  # the map they kept
        return registered._replace(maps=maps, correlation=correlation, registered=~lost)

    monkeypatch.setattr(video, "camera_motion", refusing)
    moved = load_observation(tmp_path, fps=60.0)
    kept = load_observation(tmp_path, fps=60.0, settings=SegmentationSettings(stabilise=False))
    assert moved.stabilised and not kept.stabilised
    np.testing.assert_array_equal(moved.camera_registered, ~lost)
    assert list(np.array(moved.reasons)[lost]) == ["camera move not measured"] * 2
    assert moved.used[~lost].all() and not moved.used[lost].any()
    assert "2 of 20 frames (8-9) did not register" in camera_motion_note(moved)
    assert "left out of the fit" in camera_motion_note(moved)
    fields = camera_motion_fields(moved)
    assert fields["camera_registered"] == (~lost).tolist()
    assert fields["camera_correlation"][8] == 0.5 and fields["camera_correlation"][9] is None
    assert kept.used[lost].all() and "would not be seen" in camera_motion_note(kept)


def test_one_frame_with_a_large_change_does_not_teach_the_objects_colour(tmp_path):
    """A still clip with a hand-sized patch (80 x 80 px) before the lens in frame 8 alone: that
    frame's seed is 30 times the disc's, and learnt from, its colours would be taken for the
    object's and the disc lost in other frames (12 of 20 once did). Every other frame keeps its
    disc's area (193-196 px); frame 8 is not used."""
    frames = _shaken_scene(np.tile(np.eye(3), (20, 1, 1)))
    frames[8, 10:90, 20:100] = (90, 120, 60)
    for t, frame in enumerate(frames):
        cv2.imwrite(str(tmp_path / f"{t:03d}.png"), frame)
    observation = load_observation(tmp_path, fps=60.0)
    others = np.arange(20) != 8
    assert observation.used[others].all() and not observation.used[8]
    assert observation.areas[others].min() > 185 and observation.areas[others].max() < 205


def test_frame_spans():
    from torchfit.video import _frame_spans

    assert _frame_spans(np.array([3, 7, 8, 9, 12])) == "3, 7-9, 12"
    assert _frame_spans(np.array([0])) == "0"


@pytest.mark.parametrize("value", ["yes", 1, None])
def test_stabilise_takes_true_false_or_auto(value):
    with pytest.raises(ValueError, match=f'stabilise must be true, false or "auto", got {value!r}'):
        SegmentationSettings(stabilise=value)
    for good in (True, False, "auto"):
        assert SegmentationSettings(stabilise=good).stabilise == good
