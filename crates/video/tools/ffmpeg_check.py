"""Decodes our mp4 files with FFmpeg (through PyAV) as a second opinion on the container and the
H.264 stream: frame count, size, frame rate, profile, colour signalling, keyframes, and PSNR
against the frames that were pushed. By hand only; CI does not need Python.

    pip install av==16.0.1 numpy==2.1.3
    cargo run -p gagavatar-video --example write_sample -- /tmp/v.mp4 512 512 60 25
    python3 crates/video/tools/ffmpeg_check.py /tmp/v.mp4 512 512 60 25

Without --watermark the PSNR should be near 40 dB (FFmpeg's own YUV to RGB conversion).
"""

import sys

import av
import numpy as np


def main():
    path, w, h, n, fps = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5])
    c = av.open(path)
    s = c.streams.video[0]
    cc = s.codec_context
    print(f"{path}: {c.format.name}, {cc.name} {cc.profile}, {cc.pix_fmt}, {cc.width}x{cc.height}, "
          f"rate {s.average_rate} (time base {s.time_base}), {s.frames} frames in the index, "
          f"primaries {cc.color_primaries} transfer {cc.color_trc} matrix {cc.colorspace} range {cc.color_range}, "
          f"B-frames {cc.has_b_frames}")
    ref = np.fromfile(path + ".rgb", dtype=np.uint8).reshape(n, h, w, 3).astype(np.float64)
    frames = list(c.decode(video=0))
    keys = [i for i, f in enumerate(frames) if f.key_frame]
    psnr = []
    for i, f in enumerate(frames):
        rgb = f.to_ndarray(format="rgb24").astype(np.float64)[:h, :w]
        psnr.append(10 * np.log10(255**2 / ((rgb - ref[i]) ** 2).mean()))
    print(f"decoded {len(frames)} frames, keyframes at {keys}, PSNR min {min(psnr):.2f} mean {np.mean(psnr):.2f} dB")
    assert len(frames) == n, f"expected {n} frames"
    assert (cc.width, cc.height) == (w + w % 2, h + h % 2), "size"
    assert abs(float(s.average_rate) - fps) < 1e-6, "frame rate"
    assert cc.pix_fmt == "yuv420p"


if __name__ == "__main__":
    main()
