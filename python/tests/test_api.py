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
        lambda: ga.Engine(DEMO / "weights.safetensors", precision="fp8"),
        lambda: ga.Engine(DEMO / "weights.safetensors", gpu_precision="f8"),
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


def test_bf16_renders_close_to_f32(avatar, source):
    """`precision="bf16"`: the same frame within bf16's rounding (the library's test bounds it),
    or one clear error on a CPU without AVX512-BF16."""
    flags = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    if "avx512_bf16" not in flags or "avx512bw" not in flags:
        with pytest.raises(ga.Error, match="AVX512-BF16"):
            ga.Engine.demo(precision="bf16")
        return
    low = ga.Engine.demo(precision="bf16").avatar(DEMO / "source.png", source)
    a = avatar.render(source, watermark=False)[0].astype(np.int16)
    b = low.render(source, watermark=False)[0].astype(np.int16)
    assert a.shape == b.shape
    assert np.abs(a - b).max() <= 6
    assert (a != b).any(), "bf16 changed no byte: is it running?"


def test_the_gpu_drive_matches_the_cpu(source):
    try:
        gpu = ga.Engine.demo(device="gpu", gpu_precision="f32")
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


def _clip(folder: Path) -> Path:
    """Six 256x256 frames of the public-domain astronaut photo through a drifting window, as a
    folder of PNGs (a video input that needs no decoder)."""
    photo = Image.open(DEMO / "astronaut.jpg").convert("RGB")
    folder.mkdir()
    for i in range(6):
        view = photo.crop((90 + 4 * i, 0, 370 + 4 * i, 280)).resize((256, 256), Image.BILINEAR)
        view.save(folder / f"f{i:03d}.png")
    return folder


def test_a_photo_tracked_from_python_renders_as_the_cli_does(engine, tmp_path):
    photo = DEMO / "astronaut.jpg"
    src = engine.track(photo, output=tmp_path / "py")
    assert src.kind == "photo" and not src.cached and src.names == ["astronaut_0"]
    assert src.crop.shape == (512, 512, 3) and src.crop.dtype == np.uint8
    assert src.record["shapecode"].dtype == np.float32
    # The CLI's own tracking of the same photo, and its reenactment from that folder.
    cli_dir = tmp_path / "cli_track"
    subprocess.run([cli(), "track", str(photo), "-o", str(cli_dir)], check=True,
                   capture_output=True)
    theirs_rec = ga.read_record(cli_dir / "optim.pkl", "astronaut_0")
    for k in ga.RECORD_KEYS:
        np.testing.assert_array_equal(src.record[k], theirs_rec[k], err_msg=k)
    out = tmp_path / "frames"
    subprocess.run(
        [cli(), "reenact", "--ckpt", str(DEMO / "weights.safetensors"), "--source", str(cli_dir),
         "--driver", str(DEMO / "driver.json"), "--max-frames", "2", "--batch", "2",
         "--no-watermark", "--device", "cpu", "-o", f"{out}/"],
        check=True, capture_output=True,
    )
    ours = engine.avatar(src).render(ga.read_driver(DEMO / "driver.json").records[:2], batch=2,
                                     watermark=False)
    for k in range(2):
        theirs = np.asarray(Image.open(out / f"frame_{k:05d}.png").convert("RGB"))
        assert np.array_equal(ours[k], theirs), f"frame {k} differs from the CLI's"

    # An array is tracked in memory; a wall is not a face.
    mem = engine.track(np.asarray(Image.open(photo).convert("RGB")))
    assert mem.dir is None and mem.crop.shape == (512, 512, 3)
    assert engine.avatar(mem).render(mem).shape == (1, 64, 64, 3)
    wall = np.tile(np.arange(160, dtype=np.uint8)[None, :, None], (120, 1, 3))
    with pytest.raises(ga.Error, match="no face found in the image"):
        engine.track(wall)
    with pytest.raises(ga.Error, match="not a source"):
        engine.avatar(ga.Tracked(["a_0"], [src.record], 25.0, "video"))


def test_a_video_reports_progress_is_cached_and_stops_when_asked(engine, tmp_path, monkeypatch):
    monkeypatch.setenv("GAGAVATAR_CACHE", str(tmp_path / "cache"))
    clip = _clip(tmp_path / "clip")
    seen = []
    drv = engine.track(clip, progress=lambda stage, done, total: seen.append((stage, done, total)))
    assert drv.kind == "video" and not drv.cached and len(drv) == 6
    assert drv.names == [f"clip_{i}" for i in range(6)]
    assert [s for s in dict.fromkeys(s for s, _, _ in seen)] == [
        "landmarks", "fit | crop, matte, JPEG"]
    assert seen[-1] == ("fit | crop, matte, JPEG", 12, 12)
    before = len(seen)
    again = engine.track(clip, progress=lambda *a: seen.append(a))
    assert again.cached and again.dir == drv.dir and again.fps == drv.fps
    assert len(seen) == before, "a cache hit tracks nothing, so reports nothing"
    for a, b in zip(drv.records, again.records):
        for k in ga.RECORD_KEYS:
            np.testing.assert_array_equal(a[k], b[k])
    # The tracked clip drives an avatar.
    av = engine.avatar(DEMO / "source.png", ga.read_record(DEMO / "source.json"))
    assert av.render(drv, watermark=False).shape == (6, 64, 64, 3)

    # A callback that raises stops the run; its exception comes out and nothing is left.
    class Stop(Exception):
        pass

    def stop(stage, done, total):
        if done >= 3:
            raise Stop()

    with pytest.raises(Stop):
        engine.track(clip, output=tmp_path / "stopped", progress=stop)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache", "clip"]


def test_render_many_batches_several_avatars(engine, avatar, source):
    photo = engine.track(np.asarray(Image.open(DEMO / "astronaut.jpg").convert("RGB")))
    other = engine.avatar(photo)
    driver = ga.read_driver(DEMO / "driver.json").records[:2]
    jobs = [(avatar, driver[0]), (other, driver[0]), (avatar, driver[1])]
    many = ga.render_many(jobs, watermark=False)
    assert many.shape == (3, 64, 64, 3)
    for i, (av, rec) in enumerate(jobs):
        alone = av.render(rec, watermark=False)[0]
        worst = np.abs(many[i].astype(int) - alone.astype(int)).max()
        assert worst <= 1, f"frame {i}: {worst} levels from the avatar's own render"
    with pytest.raises(ga.Error, match="not an Avatar"):
        ga.render_many([(source, source)])
    with pytest.raises(ga.Error, match="at least one"):
        ga.render_many([])
