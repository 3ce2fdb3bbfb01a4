//! Training datasets: the release layout (Python-written fixture), our folder layout, and the
//! release layout written by us.

// The same fixtures as the formats crate's tests (temporary folders, pickles, LMDBs).
#[path = "../../formats/tests/common/mod.rs"]
mod common;

use std::collections::BTreeMap;

use common::{copy_dir, data, f32s, hex, TempDir};
use gagavatar_data::dataset::{read_records_json, write_release_dataset, DatasetSplits};
use gagavatar_data::{encode_png, DataError, Dataset, ReleaseDataset, TrackedFrame};

#[test]
fn release_layout_reads() {
    let exp = common::read_json("release_small/expected.json");
    let ds = Dataset::open(&data("release_small")).unwrap();
    assert!(matches!(ds, Dataset::Release(_)));
    assert_eq!(
        ds.splits().train,
        ["spk_a_0", "spk_a_1", "spk_a_10", "spk_a_2"]
    );
    assert_eq!(ds.splits().val, ["spk_b_x_0", "spk_b_x_3"]);
    assert!(ds.splits().test.is_empty());
    let videos = ds.videos();
    assert_eq!(videos.len(), 2);
    assert_eq!(
        videos["spk_a"],
        ["spk_a_0", "spk_a_1", "spk_a_2", "spk_a_10"]
    );
    assert_eq!(videos["spk_b_x"], ["spk_b_x_0", "spk_b_x_3"]);
    assert_eq!(ds.names().len(), 6);
    for name in ds.names() {
        let r = ds.record(&name).unwrap();
        let want = f32s(
            exp["records"][&name]["transform_matrix"]["hex"]
                .as_str()
                .unwrap(),
        );
        let got: Vec<f64> = r
            .transform_matrix
            .unwrap()
            .iter()
            .flatten()
            .copied()
            .collect();
        assert_eq!(
            got,
            want.iter().map(|&x| f64::from(x)).collect::<Vec<_>>(),
            "{name}"
        );
        let img = ds.image(&name).unwrap();
        assert_eq!((img.width(), img.height()), (8, 8), "{name}");
        if name != exp["jpeg_frame"] {
            assert_eq!(
                img.as_raw(),
                &hex(exp["pixels"][&name].as_str().unwrap()),
                "{name}"
            );
        }
    }
    let e = ds.record("spk_c_0").unwrap_err().to_string();
    assert!(
        e.contains("no entry `spk_c_0`") && e.contains("6 entries, e.g. spk_a_0"),
        "{e}"
    );
    assert!(ds.image("spk_c_0").is_err());
}

#[test]
fn release_layout_checks_its_parts() {
    let dir = TempDir::new("ds-broken");
    let root = dir.path().join("ds");
    copy_dir(&data("release_small"), &root);
    // A split naming an unknown frame.
    let mut splits = DatasetSplits::read(&root.join("dataset.json")).unwrap();
    splits.test.push("spk_z_9".into());
    splits.write(&root.join("dataset.json")).unwrap();
    let e = ReleaseDataset::open(&root).unwrap_err().to_string();
    assert!(
        e.contains("dataset.json") && e.contains("`test` names frame `spk_z_9`"),
        "{e}"
    );
    // Without dataset.json every frame is in train.
    std::fs::remove_file(root.join("dataset.json")).unwrap();
    let ds = ReleaseDataset::open(&root).unwrap();
    assert_eq!(ds.splits().train.len(), 6);
    assert_eq!(ds.splits().train[3], "spk_a_10");
    // A corrupt LMDB.
    let mdb = root.join("img_lmdb/data.mdb");
    let mut bytes = std::fs::read(&mdb).unwrap();
    bytes.truncate(5000);
    std::fs::write(&mdb, bytes).unwrap();
    let e = Dataset::open(&root).unwrap_err().to_string();
    assert!(e.contains("data.mdb") && e.contains("truncated"), "{e}");
    // Missing parts.
    std::fs::remove_dir_all(root.join("img_lmdb")).unwrap();
    let e = Dataset::open(&root).unwrap_err().to_string();
    assert!(e.contains("img_lmdb is missing"), "{e}");
    let e = Dataset::open(dir.path()).unwrap_err().to_string();
    assert!(e.contains("not a dataset"), "{e}");
    // Bad dataset.json.
    std::fs::write(root.join("dataset.json"), "{\"val\": []}").unwrap();
    let e = DatasetSplits::read(&root.join("dataset.json"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("dataset.json") && e.contains("train"), "{e}");
}

fn frame(k: usize, bbox: bool) -> TrackedFrame {
    TrackedFrame {
        shapecode: (0..300)
            .map(|i| ((i * 7 + k) % 13) as f64 * 0.125 - 0.75)
            .collect(),
        expcode: (0..100).map(|i| ((i + k) % 5) as f64 * 0.25).collect(),
        posecode: vec![0.0, 0.0, 0.0, 0.125 * k as f64, 0.0, 0.0],
        eyecode: vec![0.0; 6],
        transform_matrix: Some([
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 9.0 + k as f64],
        ]),
        bbox: bbox.then_some([0.25, 0.25, 0.75, 0.75]),
    }
}

fn pixels(k: usize) -> image::RgbImage {
    image::RgbImage::from_fn(6, 4, |x, y| {
        image::Rgb([(x * 40) as u8, (y * 60) as u8, (k * 30) as u8])
    })
}

#[test]
fn folder_layout_reads_and_checks() {
    let dir = TempDir::new("ds-folder");
    let root = dir.path();
    std::fs::create_dir_all(root.join("images")).unwrap();
    let names = ["v_one_0", "v_one_5", "v_two_1"];
    let mut doc = serde_json::Map::new();
    for (k, name) in names.iter().enumerate() {
        let f = frame(k, true);
        let tm: Vec<Vec<f64>> = f
            .transform_matrix
            .unwrap()
            .iter()
            .map(|r| r.to_vec())
            .collect();
        doc.insert(
            name.to_string(),
            serde_json::json!({
                "shapecode": f.shapecode, "expcode": f.expcode, "posecode": f.posecode,
                "eyecode": f.eyecode, "transform_matrix": tm, "bbox": f.bbox.unwrap(),
            }),
        );
        pixels(k)
            .save(root.join(format!("images/{name}.png")))
            .unwrap();
    }
    std::fs::write(
        root.join("records.json"),
        serde_json::to_string(&doc).unwrap(),
    )
    .unwrap();
    let ds = Dataset::open(root).unwrap();
    assert!(matches!(ds, Dataset::Folder(_)));
    assert_eq!(ds.splits().train, names);
    assert_eq!(ds.videos()["v_one"], ["v_one_0", "v_one_5"]);
    assert_eq!(ds.record("v_two_1").unwrap(), &frame(2, true));
    assert_eq!(ds.image("v_one_5").unwrap(), pixels(1));

    // A missing image and a record without bbox are named.
    std::fs::remove_file(root.join("images/v_one_5.png")).unwrap();
    let e = Dataset::open(root).unwrap_err().to_string();
    assert!(e.contains("no image for frame `v_one_5`"), "{e}");
    pixels(1).save(root.join("images/v_one_5.png")).unwrap();
    doc.get_mut("v_two_1")
        .unwrap()
        .as_object_mut()
        .unwrap()
        .remove("bbox");
    std::fs::write(
        root.join("records.json"),
        serde_json::to_string(&doc).unwrap(),
    )
    .unwrap();
    let e = Dataset::open(root).unwrap_err();
    assert!(
        matches!(&e, DataError::Record { field, .. } if field == "bbox"),
        "{e}"
    );
    doc.get_mut("v_two_1")
        .unwrap()
        .as_object_mut()
        .unwrap()
        .remove("expcode");
    std::fs::write(
        root.join("records.json"),
        serde_json::to_string(&doc).unwrap(),
    )
    .unwrap();
    let e = read_records_json(&root.join("records.json"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("frame `v_two_1`: field `expcode`: is missing"),
        "{e}"
    );
}

#[test]
fn release_layout_written_by_us_reads_back() {
    let dir = TempDir::new("ds-write");
    let root = dir.path().join("synthetic");
    let names = ["id_a_0", "id_a_1", "id_a_2", "id_b_0", "id_b_10"];
    let records: BTreeMap<String, TrackedFrame> = names
        .iter()
        .enumerate()
        .map(|(k, n)| (n.to_string(), frame(k, true)))
        .collect();
    let images: Vec<(String, Vec<u8>)> = names
        .iter()
        .enumerate()
        .map(|(k, n)| (n.to_string(), encode_png(&pixels(k)).unwrap()))
        .collect();
    let splits = DatasetSplits {
        train: names[..3].iter().map(|s| s.to_string()).collect(),
        val: vec!["id_b_0".into()],
        test: vec!["id_b_10".into()],
    };
    let ds = write_release_dataset(&root, &records, images, &splits).unwrap();
    assert_eq!(ds.splits(), &splits);
    assert_eq!(ds.records(), &records);
    let ds = Dataset::open(&root).unwrap();
    for (k, n) in names.iter().enumerate() {
        assert_eq!(ds.image(n).unwrap(), pixels(k), "{n}");
        assert_eq!(ds.record(n).unwrap(), &records[*n], "{n}");
    }
    assert_eq!(ds.videos()["id_b"], ["id_b_0", "id_b_10"]);
    // Only the three parts, no temporary names left.
    let mut entries: Vec<String> = std::fs::read_dir(&root)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    entries.sort();
    assert_eq!(entries, ["dataset.json", "img_lmdb", "optim.pkl"]);
}

/// The training loop will read from several threads.
#[test]
fn readers_can_be_shared_between_threads() {
    fn shared<T: Send + Sync>() {}
    shared::<Dataset>();
    shared::<gagavatar_data::DriverSequence>();
    shared::<gagavatar_data::LmdbReader>();
    let ds = Dataset::open(&data("release_small")).unwrap();
    let names = ds.names();
    std::thread::scope(|s| {
        let handles: Vec<_> = names
            .iter()
            .map(|n| s.spawn(|| ds.image(n).map(|i| i.width())))
            .collect();
        for h in handles {
            assert_eq!(h.join().unwrap().unwrap(), 8);
        }
    });
}
