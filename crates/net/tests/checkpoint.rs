//! Reading weights in the release container (torch zip, `{"model": ..., "meta_cfg": ...}`) and
//! safetensors, converting between them, seeded init, and corrupt files.

use std::collections::BTreeMap;
use std::path::PathBuf;

use candle_core::{DType, Device, Tensor};
use gagavatar_net::checkpoint::{
    self, check_keys, init_weights, load_model, read_weights, write_tensors,
};
use gagavatar_net::{ModelConfig, NetError};

fn golden(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/golden")
        .join(name)
}

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("gagavatar-net-ckpt-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

fn same(a: &Tensor, b: &Tensor) -> bool {
    a.dims() == b.dims()
        && a.flatten_all().unwrap().to_vec1::<f32>().unwrap()
            == b.flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

#[test]
fn release_container_reads_like_the_safetensors() {
    let pt = read_weights(&golden("tiny_release_format.pt")).unwrap();
    let st = read_weights(&golden("tiny_weights.safetensors")).unwrap();
    assert!(
        pt.config.is_none(),
        "the release .pt has no gagavatar config"
    );
    for (k, t) in &st.tensors {
        let p = pt
            .tensors
            .get(k)
            .unwrap_or_else(|| panic!("{k} missing from the .pt"));
        assert!(same(p, t), "{k} differs between .pt and safetensors");
    }
    // Everything else in the .pt is the perceptual-loss weights, which check_keys accepts.
    let extra: Vec<_> = pt
        .tensors
        .keys()
        .filter(|k| !st.tensors.contains_key(*k))
        .collect();
    assert_eq!(extra, ["percep_loss.vggface.network.0.weight"]);
    check_keys(&ModelConfig::tiny(), &pt.tensors).unwrap();
    // Without a preset the .pt means the release architecture: a clear key error, not garbage.
    let err = load_model(&golden("tiny_release_format.pt"), None, &Device::Cpu).unwrap_err();
    assert!(matches!(err, NetError::Keys { .. }), "{err}");
    assert!(err.to_string().contains("misshapen"), "{err}");
    load_model(
        &golden("tiny_release_format.pt"),
        Some(&ModelConfig::tiny()),
        &Device::Cpu,
    )
    .unwrap();
}

#[test]
fn convert_round_trips_and_records_the_config() {
    let pt = read_weights(&golden("tiny_release_format.pt")).unwrap();
    let out = tmp("converted.safetensors");
    let tensors: BTreeMap<String, Tensor> = pt.tensors.clone().into_iter().collect();
    write_tensors(&out, &tensors, Some(&ModelConfig::tiny())).unwrap();
    let back = read_weights(&out).unwrap();
    assert_eq!(back.config, Some(ModelConfig::tiny()));
    assert_eq!(back.tensors.len(), pt.tensors.len());
    for (k, t) in &pt.tensors {
        assert!(same(&back.tensors[k], t), "{k} changed in the round trip");
    }
    // The stored config is enough to load it.
    load_model(&out, None, &Device::Cpu).unwrap();
    // No temp file is left beside the output.
    let leftovers: Vec<_> = std::fs::read_dir(out.parent().unwrap())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().contains(".tmp"))
        .collect();
    assert!(leftovers.is_empty());
}

#[test]
fn init_weights_is_seeded_and_complete() {
    let cfg = ModelConfig::tiny();
    let a = init_weights(&cfg, 5).unwrap();
    let b = init_weights(&cfg, 5).unwrap();
    let c = init_weights(&cfg, 6).unwrap();
    assert_eq!(a, b, "same seed, same weights");
    assert_ne!(
        a["head_base"], c["head_base"],
        "another seed, other weights"
    );
    let keys = checkpoint::expected_keys(&cfg).unwrap();
    assert_eq!(a.len(), keys.len());
    for (k, (shape, v)) in &a {
        assert_eq!(&keys[k], shape, "{k}");
        assert!(v.iter().all(|x| x.is_finite()), "{k} has non-finite values");
    }
    // Fan-in scaling keeps a conv's weights around 1/sqrt(fan_in), not N(0,1).
    let (s, w) = &a["gs_generator_l0.gaussian_conv.2.weight"];
    let fan_in = (s[1] * s[2] * s[3]) as f64;
    let var = w.iter().map(|x| (*x as f64).powi(2)).sum::<f64>() / w.len() as f64;
    assert!(
        (var * fan_in - 1.0).abs() < 0.2,
        "variance x fan_in = {}",
        var * fan_in
    );
}

#[test]
fn corrupt_and_wrong_files_are_clear_errors() {
    let junk = tmp("junk.safetensors");
    std::fs::write(&junk, b"not a checkpoint at all").unwrap();
    let e = read_weights(&junk).err().expect("junk must not load");
    assert!(
        e.to_string()
            .contains("neither a torch zip nor safetensors"),
        "{e}"
    );
    let trunc = tmp("truncated.pt");
    let bytes = std::fs::read(golden("tiny_release_format.pt")).unwrap();
    std::fs::write(&trunc, &bytes[..bytes.len() / 2]).unwrap();
    assert!(read_weights(&trunc).is_err());
    let missing = tmp("does-not-exist.pt");
    let e = read_weights(&missing).err().expect("missing file");
    assert!(matches!(e, NetError::Io { .. }), "{e}");
    // An integer tensor where weights are expected.
    let bad = tmp("int.safetensors");
    let mut m = std::collections::HashMap::new();
    m.insert(
        "head_base".to_string(),
        Tensor::zeros(3, DType::I64, &Device::Cpu).unwrap(),
    );
    candle_core::safetensors::save(&m, &bad).unwrap();
    let e = read_weights(&bad).err().expect("int weights");
    assert!(e.to_string().contains("floating point"), "{e}");
}

/// The torch checkpoint writer: the tiny model plus edge-case tensors (a 0-d scalar, NaN, -0.0,
/// subnormals) read back bit for bit, in torch's archive layout.
#[test]
fn torch_checkpoint_round_trips_bit_exactly() {
    use gagavatar_net::checkpoint::write_torch_checkpoint;

    let cfg = ModelConfig::tiny();
    let mut tensors: BTreeMap<String, Tensor> = init_weights(&cfg, 1)
        .unwrap()
        .into_iter()
        .map(|(k, (s, v))| (k, Tensor::from_vec(v, s, &Device::Cpu).unwrap()))
        .collect();
    let odd = vec![
        f32::NAN,
        -0.0,
        f32::from_bits(1),
        f32::MAX,
        f32::NEG_INFINITY,
        1.5,
    ];
    tensors.insert(
        "percep_loss.odd".into(),
        Tensor::from_vec(odd, (2, 3), &Device::Cpu).unwrap(),
    );
    tensors.insert(
        "percep_loss.scalar".into(),
        Tensor::new(7.25f32, &Device::Cpu).unwrap(),
    );
    let path = tmp("torch_writer.pt");
    write_torch_checkpoint(&path, &tensors, Some(&cfg)).unwrap();

    let back = read_weights(&path).unwrap();
    assert_eq!(back.tensors.len(), tensors.len(), "tensor count");
    for (k, want) in &tensors {
        let got = back
            .tensors
            .get(k)
            .unwrap_or_else(|| panic!("`{k}` missing"));
        assert_eq!(got.dims(), want.dims(), "`{k}` shape");
        let w = want.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let g = got.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        for (i, (a, b)) in w.iter().zip(&g).enumerate() {
            assert_eq!(
                a.to_bits(),
                b.to_bits(),
                "`{k}`[{i}]: expected {a:e}, got {b:e}"
            );
        }
    }
    check_keys(&cfg, &back.tensors).unwrap();

    // The archive layout torch needs is tested with the writer in `gagavatar-formats`.
    // The writer leaves no temp sibling behind.
    let dir = path.parent().unwrap();
    let leftovers: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains("torch_writer.pt") && n != "torch_writer.pt")
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

#[test]
fn named_weights_give_back_every_key_and_value_the_model_was_built_from() {
    let cfg = ModelConfig::tiny();
    let data = init_weights(&cfg, 3).unwrap();
    let dev = Device::Cpu;
    let tensors = data
        .iter()
        .map(|(k, (shape, v))| {
            (
                k.clone(),
                Tensor::from_vec(v.clone(), shape.as_slice(), &dev).unwrap(),
            )
        })
        .collect();
    let model = checkpoint::build_model(&cfg, tensors, &dev).unwrap();
    let named = model.named_weights().unwrap();
    let mut seen = BTreeMap::new();
    for (k, t) in &named {
        assert!(seen.insert(k.clone(), ()).is_none(), "{k} listed twice");
        let (shape, v) = data
            .get(k)
            .unwrap_or_else(|| panic!("{k} is not a checkpoint key"));
        assert_eq!(
            t.elem_count(),
            shape.iter().product::<usize>(),
            "{k}: {:?} against the checkpoint's {shape:?}",
            t.dims()
        );
        let got = t
            .to_dtype(DType::F32)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        assert!(&got == v, "{k}: values differ from the file's");
    }
    let missing: Vec<&String> = data
        .keys()
        .filter(|k| !seen.contains_key(*k) && !k.starts_with("upsampler.toRGB."))
        .collect();
    assert!(missing.is_empty(), "not listed: {missing:?}");
}
