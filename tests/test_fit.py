"""End-to-end: Hydra configs, the search and the outputs, on the shipped recordings (CPU)."""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hydra import compose, initialize_config_module
from hydra.errors import ConfigCompositionException

from torchfit.provenance import file_digest
from torchfit.run import run

SMALL = Path(__file__).resolve().parents[1] / "torchfit" / "recordings" / "tshape_small"
EXPERIMENTS = sorted(p.stem for p in (Path(__file__).resolve().parents[1] / "torchfit" / "configs"
                                      / "experiment").glob("*.yaml"))
TWO_STEPS = ["search=quick", "search.orientations=60", "search.anchor_steps=2", "search.survivors=4",
             "search.stages=[[1.0,16,1.5,2,1.0]]", "search.polish_iterations=2", "search.polish_crop=16",
             "outputs.overlay_video=false", "outputs.plots=false", "quiet=true"]
SMALL_DATA = [f"data.video={SMALL / 'video.mp4'}", f"object.mesh={SMALL / 'mesh.obj'}",
              f"camera.file={SMALL / 'camera.json'}", f"data.truth={SMALL / 'truth.json'}"]


def _compose(overrides):
    with initialize_config_module(config_module="torchfit.configs", version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_experiment_config_runs_two_steps(experiment, tmp_path):
    extra = SMALL_DATA if experiment == "fit" else []
    cfg = _compose([f"experiment={experiment}", *TWO_STEPS, *extra])
    if cfg.task != "fit":  # an experiment of its own: its quick version, a summary.json
        cfg = _compose([f"experiment={experiment}", *TWO_STEPS, "params.quick=true"])
        summary = run(cfg, tmp_path)
        assert json.loads((tmp_path / "summary.json").read_text()) == json.loads(json.dumps(summary))
        return
    content = run(cfg, tmp_path)
    assert (tmp_path / "result.json").exists()
    assert len(content["per_frame"]["frame"]) == len(content["per_frame"]["iou"])
    assert np.isfinite(content["loss"])


def test_fit_small_recording_end_to_end(tmp_path):
    cfg = _compose(["experiment=fit", "search=quick", *SMALL_DATA])
    content = run(cfg, tmp_path)
    result = json.loads((tmp_path / "result.json").read_text())
    params = result["params"]
    assert set(params) >= {"position", "orientation_wxyz", "R", "velocity", "angular_velocity", "gravity_dir",
                           "tilt_deg", "roll_deg"}
    np.testing.assert_allclose(np.asarray(params["R"]) @ np.asarray(params["R"]).T, np.eye(3), atol=1e-6)
    per_frame = result["per_frame"]
    assert len(per_frame["frame"]) == 12 and per_frame["time"][0] == 0.0
    assert result["provenance"]["source_sha256"] == file_digest(SMALL / "video.mp4")
    # filmed from a still camera: each frame's background offset measured, none moved back
    assert np.array(result["camera_motion_px"]).shape == (12, 2) and result["stabilised"] is False
    assert len(result["camera_turn_deg"]) == 12
    maps = np.array(result["camera_maps"])  # each frame's homography, near the identity
    assert maps.shape == (12, 3, 3) and np.abs(maps[:, :2, 2]).max() < 0.25
    assert result["camera_registered"] == [True] * 12 and min(result["camera_correlation"]) > 0.9
    assert len(result["camera_sigma_px"]) == 12 and 0 < min(result["camera_sigma_px"]) < max(result["camera_sigma_px"]) < 0.25
    assert np.abs(maps[:, :2, :2] - np.eye(2)).max() < 1e-3 and np.abs(maps[:, 2, :2]).max() < 1e-5
    for name in ("iou.png", "loss.png", "overlay.mp4", "contact_sheet.png"):
        assert (tmp_path / name).stat().st_size > 0
    # the quick search on the 320x240 tshape_small clip: orientation found, silhouettes overlap well
    assert content["truth"]["rotation_error_deg"] < 10.0
    assert content["mean_iou"] > 0.6
    assert result["candidates"][0]["loss"] <= min(c["loss"] for c in result["candidates"])


def test_fit_is_deterministic_for_a_seed(tmp_path):
    first = run(_compose(["experiment=fit", *TWO_STEPS, *SMALL_DATA]), tmp_path / "a")
    second = run(_compose(["experiment=fit", *TWO_STEPS, *SMALL_DATA]), tmp_path / "b")
    assert first["params"] == second["params"]


def test_default_search_config_is_the_dataclass_default():
    from torchfit.run import _search_settings
    from torchfit.search import SearchSettings

    cfg = _compose(["experiment=tshape"])
    assert _search_settings(cfg.search) == SearchSettings(seed=int(cfg.seed))


def test_mistyped_key_fails():
    with pytest.raises(ConfigCompositionException, match="orientationz"):
        _compose(["experiment=fit", "search.orientationz=5"])


@pytest.mark.parametrize("override, message", [
    ("data.fps=-5", "data.fps must be positive"),
    ("search.survivors=0", "search.survivors must be a positive count"),
    ("search.stages=[[1.0,16,1.5,2]]", "search.stages entries"),
    ("device=tpu", "device must be auto, cpu or cuda"),
    ("threads=0", "threads must be auto or an integer >= 1, got 0"),
    ("threads=many", "threads must be auto or an integer >= 1, got 'many'"),
])
def test_bad_config_values_raise(override, message, tmp_path):
    with pytest.raises(ValueError, match=message):
        run(_compose(["experiment=fit", *TWO_STEPS, *SMALL_DATA, override]), tmp_path)


@pytest.mark.parametrize("busy, expected", [(0, 4), (1, 3), (3, 1), (9, 1)])
def test_auto_threads_leave_the_busy_cores(monkeypatch, busy, expected):
    import torchfit.run as run_module

    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3}, raising=False)
    monkeypatch.setattr(run_module, "_busy_cores", lambda: busy)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert run_module.resolve_threads("auto") == expected
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    assert run_module.resolve_threads("auto") == min(expected, 2)
    assert run_module.resolve_threads(3) == 3


@pytest.mark.skipif(not Path("/proc/loadavg").exists(), reason="counts runnable tasks from Linux's /proc")
def test_a_busy_process_counts_as_a_busy_core():
    from torchfit.run import _busy_cores

    idle = _busy_cores()
    spinner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.5)
        assert _busy_cores() >= min(idle + 1, 1)
    finally:
        spinner.kill()
        spinner.wait()


def test_run_uses_the_threads_it_is_given(tmp_path):
    import torch

    before = torch.get_num_threads()
    try:
        run(_compose(["experiment=fit", *TWO_STEPS, *SMALL_DATA, "threads=1"]), tmp_path)
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_millimetre_mesh_is_rejected(tmp_path):
    mesh = trimesh.load(SMALL / "mesh.obj", force="mesh")
    mesh.apply_scale(1000.0)
    path = tmp_path / "mesh_mm.obj"
    mesh.export(path)
    with pytest.raises(ValueError, match="millimetres given as metres"):
        run(_compose(["experiment=fit", *TWO_STEPS, *SMALL_DATA, f"object.mesh={path}"]), tmp_path)


def test_too_short_recording_is_rejected(tmp_path):
    with pytest.raises(ValueError, match="too short to fit"):
        run(_compose(["experiment=fit", *TWO_STEPS, *SMALL_DATA, "data.stop=4"]), tmp_path)


def _cli(args, cwd):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.run([sys.executable, "-m", "torchfit", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600)


def test_cli_multirun_sweep_writes_one_folder_per_run(tmp_path):
    proc = _cli(["-m", "experiment=fit", *TWO_STEPS, *SMALL_DATA, "seed=0,1"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    results = sorted(tmp_path.glob("multirun/*/*/*/result.json"))
    assert len(results) == 2


def test_cli_bad_input_is_one_line_and_nonzero(tmp_path):
    proc = _cli(["experiment=fit", *TWO_STEPS, f"data.video={tmp_path / 'missing.mp4'}",
                 f"object.mesh={SMALL / 'mesh.obj'}", f"camera.file={SMALL / 'camera.json'}"], tmp_path)
    assert proc.returncode == 2
    assert "torchfit: error:" in proc.stderr and "Traceback" not in proc.stderr


def test_configs_resolve_outside_the_checkout(tmp_path):
    # run from an empty folder: configs and the shipped recording come from the installed package
    proc = _cli(["experiment=tshape", "--cfg", "job", "--resolve"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    video = [line.split(":", 1)[1].strip() for line in proc.stdout.splitlines() if line.strip().startswith("video:")]
    assert video and Path(video[0]).is_file()


def test_segmentation_settings_come_from_the_config():
    from omegaconf import OmegaConf

    from torchfit.run import ConfigError, _segmentation_settings
    from torchfit.video import SegmentationSettings

    settings = _segmentation_settings(OmegaConf.create({"method": "median", "transfer": "bt709"}))
    assert settings.transfer == "bt709" and settings.method == "median"
    default = OmegaConf.load(Path(__file__).parents[1] / "torchfit" / "configs" / "data" / "default.yaml")
    assert _segmentation_settings(default.segmentation).transfer == "auto"  # the curve the file names
    assert _segmentation_settings(default.segmentation).albedo_passes == 0  # a fit's masks
    assert _segmentation_settings(default.segmentation, coverage=True).albedo_passes == 1  # with data.exposure
    passes = _segmentation_settings(OmegaConf.create({"method": "median", "transfer": "auto", "albedo_passes": 1}))
    assert passes.albedo_passes == 1
    with pytest.raises(ConfigError, match="data.segmentation: transfer must be one of"):
        _segmentation_settings(OmegaConf.create({"method": "median", "transfer": "gamma"}))
    assert _segmentation_settings(default.segmentation).coverage_near_px == "auto"  # 4 steps at 640 x 480
    assert _segmentation_settings(default.segmentation).band_steps(480, 640) == 4
    band = _segmentation_settings(OmegaConf.create({"method": "median", "transfer": "auto", "coverage_near_px": 8}))
    assert band.coverage_near_px == 8
    auto = _segmentation_settings(OmegaConf.create({"method": "median", "transfer": "auto", "coverage_near_px": "auto"}))
    assert auto.coverage_near_px == "auto" and auto.band_steps(960, 1280) == 8
    assert _segmentation_settings(default.segmentation).stabilise == "auto"  # moved back past STILL_PX
    for value in (True, False):
        assert _segmentation_settings(OmegaConf.create({"method": "median", "transfer": "auto",
                                                        "stabilise": value})).stabilise is value
    with pytest.raises(ConfigError, match="data.segmentation: stabilise must be true, false or \"auto\", got 'often'"):
        _segmentation_settings(OmegaConf.create({"method": "median", "transfer": "auto", "stabilise": "often"}))
    for bad in (0, 2.5, "wide"):
        with pytest.raises(ConfigError, match=f"data.segmentation: coverage_near_px must be a whole number of steps "
                                              f">= 1 or \"auto\", got {bad!r}"):
            _segmentation_settings(OmegaConf.create({"method": "median", "transfer": "auto", "coverage_near_px": bad}))
    assert _segmentation_settings(default.segmentation).well_posed_grey == SegmentationSettings().well_posed_grey
    grey = _segmentation_settings(OmegaConf.create({"method": "median", "transfer": "auto", "well_posed_grey": 5}))
    assert grey.well_posed_grey == 5.0
    for bad in ("dark", True):
        with pytest.raises(ConfigError, match=f"data.segmentation: well_posed_grey must be a number of grey levels "
                                              f">= 0, got {bad!r}"):
            _segmentation_settings(OmegaConf.create({"method": "median", "transfer": "auto", "well_posed_grey": bad}))
    with pytest.raises(ConfigError, match="data.segmentation: well_posed_grey must be >= 0, got -1.0"):
        _segmentation_settings(OmegaConf.create({"method": "median", "transfer": "auto", "well_posed_grey": -1}))
    # null: on where discover compares the soft coverage (the path measured), off elsewhere
    assert _segmentation_settings(default.segmentation, coverage=True).interior_shading is True
    assert _segmentation_settings(default.segmentation).interior_shading is False
    for value in (True, False):
        for coverage in (True, False):
            assert _segmentation_settings(OmegaConf.create({"method": "median", "transfer": "auto",
                                                            "interior_shading": value}),
                                          coverage=coverage).interior_shading is value
    for bad in (1, "yes"):
        with pytest.raises(ConfigError, match=f"data.segmentation: interior_shading must be true or false, got {bad!r}"):
            _segmentation_settings(OmegaConf.create({"method": "median", "transfer": "auto", "interior_shading": bad}))


def test_the_log_says_how_pixel_values_were_read():
    """``auto`` that found no curve in the file names the key to set; a curve found or set does not."""
    from torchfit.run import _transfer_line
    from torchfit.video import Observation, SegmentationSettings

    def observation(transfer, note):
        return Observation(masks=np.zeros((1, 2, 2), bool), boxes=np.zeros((1, 4)), used=np.ones(1, bool),
                           reasons=[""], fps=30.0, frame_indices=np.arange(1), camera=None, source="clip.mp4",
                           kind="video", transfer=transfer, transfer_note=note)

    untagged = observation("linear", "clip.mp4: no transfer curve named (H.264 stream's VUI); read as linear")
    line = _transfer_line(untagged, SegmentationSettings())
    assert line.startswith("pixel values: clip.mp4: no transfer curve named") and "data.segmentation.transfer=bt709" in line
    assert "data.segmentation" not in _transfer_line(observation("linear", "transfer linear, as set"),
                                                     SegmentationSettings(transfer="linear"))
    assert "data.segmentation" not in _transfer_line(observation("bt709", "clip.mp4: transfer 1 (bt709) from the 'colr' box"),
                                                     SegmentationSettings())
