"""The Python package against the CLI and the library's contracts: the same frames as
`gagavatar reenact` bit for bit, codes and records agreeing, watermark on by default, long
clips streamed, every bad input a `gagavatar.Error`."""

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import gagavatar as ga

REPO = Path(__file__).resolve().parents[2]
DEMO = REPO / "assets" / "demo"


def cli():
    exe = os.environ.get("GAGAVATAR_BIN") or str(REPO / "target" / "debug" / "gagavatar")
    if not Path(exe).is_file():
        pytest.fail(f"the gagavatar binary is not at {exe} (build it, or set GAGAVATAR_BIN)")
    return exe


@pytest.fixture(scope="module")
def engine():
    return ga.Engine.demo()


@pytest.fixture(scope="module")
def source():
    return ga.read_record(DEMO / "source.json")


@pytest.fixture(scope="module")
def avatar(engine, source):
    return engine.avatar(DEMO / "source.png", source)


def test_the_demo_engine_opens_with_the_flame_its_weights_name(engine):
    assert engine.image_size == 64
    assert engine.warnings == []
    assert engine.flame == "the built-in synthetic asset"
    assert engine.device == "cpu"


def test_records_are_dicts_of_arrays_in_the_release_names(source):
    assert set(source) == set(ga.RECORD_KEYS)
    assert source["shapecode"].shape == (300,) and source["shapecode"].dtype == np.float32
    assert source["transform_matrix"].shape == (3, 4)
    raw = json.loads((DEMO / "source.json").read_text())
    np.testing.assert_array_equal(source["expcode"], np.asarray(raw["expcode"], np.float32))


def test_frames_equal_the_cli_bit_for_bit(avatar, tmp_path):
    out = tmp_path / "cli"
    subprocess.run(
        [cli(), "reenact", "--ckpt", str(DEMO / "weights.safetensors"),
         "--source", str(DEMO / "source.png"), "--source-record", str(DEMO / "source.json"),
         "--driver", str(DEMO / "driver.json"), "--max-frames", "3", "--batch", "3",
         "--no-watermark", "--device", "cpu", "-o", f"{out}/"],
        check=True, capture_output=True,
    )
    driver = ga.read_driver(DEMO / "driver.json")
    ours = avatar.render(driver.records[:3], batch=3, watermark=False)
    assert ours.shape == (3, 64, 64, 3) and ours.dtype == np.uint8
    for k in range(3):
        theirs = np.asarray(Image.open(out / f"frame_{k:05d}.png").convert("RGB"))
        assert np.array_equal(ours[k], theirs), f"frame {k} differs from the CLI's"
    # With the label, as the CLI writes by default: the same frame outside the label.
    marked = avatar.render(driver.records[:1], watermark=True)[0]
    changed = np.argwhere((marked != ours[0]).any(axis=2))
    assert len(changed) > 0, "no visible label"
    assert len(changed) < 0.08 * 64 * 64


def test_codes_and_records_render_the_same_frame(avatar, source):
    by_record = avatar.render(source, watermark=False)[0]
    by_codes = avatar.render_codes(
        source["expcode"], source["posecode"][3:], source["eyecode"], watermark=False
    )
    assert np.array_equal(by_record, by_codes)
    opened = avatar.render_codes(source["expcode"], jaw=(0.3, 0, 0), watermark=False)
    assert not np.array_equal(opened, by_codes), "the jaw changed nothing"


def test_a_long_clip_streams_a_batch_at_a_time(engine, source):
    av = engine.avatar(DEMO / "source.png", source)
    driver = ga.read_driver(DEMO / "driver.json")
    assert len(driver) >= 50
    it = av.frames(driver, batch=4, watermark=False)
    first = [next(it), next(it)]
    assert first[0].shape == (64, 64, 3)
    # Two frames taken: one batch rendered, not the clip.
    assert av.frames_rendered == 4
    np.testing.assert_array_equal(first[1], av.render(driver.records[1], watermark=False)[0])


def test_orbit_ply_and_video(avatar, tmp_path):
    views = avatar.orbit(yaw=25, pitch=5, frames=6, watermark=False)
    assert views.shape == (6, 64, 64, 3)
    assert not np.array_equal(views[0], views[1])
    ply = tmp_path / "a.ply"
    avatar.export_ply(ply)
    assert ply.read_bytes().startswith(b"ply\n")
    ga.write_video(tmp_path / "o.mp4", views, fps=12)
    assert (tmp_path / "o.mp4").stat().st_size > 1000
    ga.write_video(tmp_path / "pngs", views[:2])
    assert sorted(p.name for p in (tmp_path / "pngs").iterdir()) == [
        "frame_00000.png", "frame_00001.png"]


def test_bad_inputs_raise_one_line_errors(engine, source, tmp_path):
    cases = [
        lambda: ga.Engine(tmp_path / "missing.pt"),
        lambda: ga.Engine(DEMO / "weights.safetensors", device="tpu"),
        lambda: ga.Engine(DEMO / "weights.safetensors", flame=tmp_path / "no_flame.pt"),
        lambda: engine.avatar(np.zeros((8, 8), np.uint8), source),
        lambda: engine.avatar(DEMO / "source.png", {k: v for k, v in source.items()
                                                     if k != "transform_matrix"}),
        lambda: engine.avatar(tmp_path / "missing.png", source),
        lambda: ga.read_record(tmp_path / "missing.json"),
        lambda: ga.read_driver(tmp_path / "missing_dir"),
        lambda: ga.write_video(tmp_path / "x.mp4", np.zeros((0, 8, 8, 3), np.uint8)),
    ]
    for i, case in enumerate(cases):
        with pytest.raises(ga.Error) as e:
            case()
        msg = str(e.value)
        assert msg and "\n" not in msg and "panicked" not in msg, f"case {i}: {msg}"
    with pytest.raises(ga.Error, match="no_flame.pt"):
        ga.Engine(DEMO / "weights.safetensors", flame=tmp_path / "no_flame.pt")
    av = engine.avatar(DEMO / "source.png", source)
    with pytest.raises(ga.Error, match="expression"):
        av.render_codes(np.zeros(500))
    with pytest.raises(ga.Error, match="not finite"):
        av.render_codes(camera=np.full((3, 4), np.nan))


def test_the_gpu_drive_matches_the_cpu(source):
    try:
        gpu = ga.Engine.demo(device="gpu")
    except ga.Error as e:
        if os.environ.get("GAGAVATAR_REQUIRE_GPU_TESTS", "0") not in ("", "0"):
            raise
        pytest.skip(f"no GPU device: {e}")
    cpu = ga.Engine.demo()
    driver = ga.read_driver(DEMO / "driver.json").records[:2]
    a = cpu.avatar(DEMO / "source.png", source).render(driver, watermark=False)
    b = gpu.avatar(DEMO / "source.png", source).render(driver, watermark=False)
    # The GPU's fine image is within 1e-5 of the CPU's: at most one 8-bit level.
    assert np.abs(a.astype(int) - b.astype(int)).max() <= 1
