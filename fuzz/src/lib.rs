//! Fuzz harnesses: one `fn(&[u8])` per loader of files users bring. Each feeds the bytes to the
//! production parser exactly as a file would reach it and must return normally whatever the
//! bytes are: an `Err` is the expected outcome for garbage, a panic, an abort, a hang or an
//! allocation beyond the budget is a bug.
//!
//! Two drivers run them:
//! - `tests/smoke.rs` (stable `cargo test`, in CI): the committed seed corpus under
//!   `corpus/<target>/` plus deterministic mutations for a few seconds per target, with a
//!   counting allocator and a per-case time limit.
//! - `fuzz/afl` (a separate crate, built with `cargo afl build`): coverage-guided AFL++ runs
//!   for the long campaigns; see `fuzz/README.md`.

use std::path::PathBuf;

use gagavatar_formats::image::DecodeOptions;

/// A harness: bytes in, returns normally whatever they are.
pub type Harness = fn(&[u8]);

/// Every harness by name (the corpus folder and the AFL target name).
pub const TARGETS: &[(&str, Harness)] = &[
    ("pickle", pickle),
    ("numpy", numpy),
    ("torch_zip", torch_zip),
    ("safetensors", safetensors),
    ("lmdb", lmdb),
    ("mp4", mp4),
    ("ply", ply),
    ("records_json", records_json),
    ("driving_json", driving_json),
    ("toml_config", toml_config),
    ("image", image),
    ("onnx", onnx),
];

/// The harness called `name`.
pub fn target(name: &str) -> Option<Harness> {
    TARGETS.iter().find(|(n, _)| *n == name).map(|(_, f)| *f)
}

/// The data-only pickle interpreter (any content, protocols 0-5), then the bounded rendering
/// used in error messages.
pub fn pickle(data: &[u8]) {
    if let Ok(p) = gagavatar_formats::pickle::read::parse(data) {
        let _ = p.describe(p.root());
    }
}

/// Plain data and numpy arrays out of a pickle (the tracked-record reader), and, when that
/// succeeds, our writer and reader again on the result.
pub fn numpy(data: &[u8]) {
    if let Ok(v) = gagavatar_formats::pickle::parse_pickle(data) {
        if let Ok(bytes) = gagavatar_formats::pickle::to_pickle(&v) {
            let _ = gagavatar_formats::pickle::parse_pickle(&bytes);
        }
        // What the release's optim.pkl reader makes of it.
        let _ = gagavatar_data::records::records_from_value(std::path::Path::new("fuzz.pkl"), &v);
    }
}

/// A torch zip checkpoint: the archive, its pickle, the tensor walk and every storage view.
pub fn torch_zip(data: &[u8]) {
    let _ = gagavatar_formats::torch_zip::read_torch_zip_bytes(data, "fuzz.pt");
}

/// A safetensors file: the header (JSON, offsets) and every tensor decoded.
pub fn safetensors(data: &[u8]) {
    let _ = gagavatar_formats::safetensors::read_header(data, "fuzz.safetensors");
    let _ = gagavatar_formats::safetensors::parse_safetensors(data, "fuzz.safetensors");
}

/// An LMDB environment: meta pages, the B-tree walk over every key, and every value.
pub fn lmdb(data: &[u8]) {
    let Ok(env) =
        gagavatar_formats::lmdb::LmdbReader::from_bytes("fuzz.mdb".as_ref(), data.to_vec())
    else {
        return;
    };
    let _ = env.stat();
    if let Ok(keys) = env.keys() {
        for k in keys.iter().take(64) {
            let _ = env.get(k);
        }
    }
    let _ = env.get(b"frame_0");
}

/// An mp4 / mov file: the box tree, the video track's sample tables and every sample's NAL
/// units (the demuxer), then the built-in reader's plan for it: container and codec sniffing
/// and the SPS / PPS parsing that decides whether OpenH264 may decode it (decoding itself is
/// OpenH264's; ffmpeg is never started here).
pub fn mp4(data: &[u8]) {
    let path = scratch_file("fuzz.mp4", data);
    let _ = gagavatar_video::mp4::read_mp4_info(&path);
    let _ = gagavatar_video::mp4::demux_mp4(&path);
    let opts = gagavatar_video::read::ReadOptions {
        decoder: gagavatar_video::read::DecoderChoice::OpenH264,
        ..Default::default()
    };
    let _ = gagavatar_video::read::probe(&path, &opts, false);
}

/// A 3DGS `.ply` scene.
pub fn ply(data: &[u8]) {
    let _ = gagavatar_formats::ply::parse_ply(data);
}

/// A tracked-frame record (`flame mesh --params`, `--source-record`) and a folder dataset's
/// `records.json`.
pub fn records_json(data: &[u8]) {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = gagavatar_flame::TrackedFrame::from_json_str(text);
    }
    let path = scratch_file("records.json", data);
    let _ = gagavatar_data::dataset::read_records_json(&path);
    let _ = gagavatar_data::read_source_record(&path, None);
}

/// A driving sequence `{"fps": .., "frames": [record, ...]}`.
pub fn driving_json(data: &[u8]) {
    let path = scratch_file("drive.json", data);
    let _ = gagavatar_data::DriverSequence::open(&path);
}

/// A training configuration (TOML), and, when it parses, writing it back and reading that.
pub fn toml_config(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(cfg) = gagavatar_train::config::TrainConfig::from_toml_str(text, None) {
        if let Ok(back) = cfg.to_toml_string() {
            let _ = gagavatar_train::config::TrainConfig::from_toml_str(&back, None);
        }
    }
}

/// A photo, decoded as the CLI decodes source photos (by content, EXIF orientation, size caps,
/// downscaled to fit 2048 px).
pub fn image(data: &[u8]) {
    let opts = DecodeOptions {
        min_side: 1,
        fit_within: Some(2048),
    };
    let _ = gagavatar_formats::image::decode_image(data, "fuzz", &opts);
}

/// An ONNX model (a user's ArcFace for `eval --arcface`): the hand-written protobuf reader, then
/// every node and initializer it kept.
pub fn onnx(data: &[u8]) {
    if let Ok(g) = gagavatar_formats::onnx::parse_model(data) {
        let mut n = g.inputs.len() + g.outputs.len();
        for node in &g.nodes {
            n += node.inputs.len() + node.outputs.len() + node.attributes.len();
        }
        for t in g.initializers.values() {
            n += t.dims.len();
        }
        std::hint::black_box(n);
    }
}

/// Writes `data` to a scratch file named `name` (per process and thread) for the loaders that
/// take a path, and returns its path. Set `TMPDIR` to a RAM disk for speed.
pub fn scratch_file(name: &str, data: &[u8]) -> PathBuf {
    thread_local! {
        static DIR: PathBuf = {
            let dir = std::env::temp_dir().join(format!(
                "gagavatar-fuzz-{}-{:?}",
                std::process::id(),
                std::thread::current().id()
            ));
            let _ = std::fs::create_dir_all(&dir);
            dir
        };
    }
    let path = DIR.with(|d| d.join(name));
    let _ = std::fs::write(&path, data);
    path
}
