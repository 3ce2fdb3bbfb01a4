//! Training datasets (spec sections 10-11).
//!
//! * The release layout: `img_lmdb/` (frame name -> PNG / JPEG bytes or a torch tensor),
//!   `optim.pkl` (frame name -> record) and `dataset.json` (`{"train": [...], "val": [...],
//!   "test": [...]}`).
//! * Our own layout: `images/<name>.png`, `records.json` (`{name: record}`, records as in
//!   `TrackedFrame` JSON) and the same `dataset.json`.
//!
//! In both, `dataset.json` may be absent (every frame is then in `train`), and opening checks
//! that every frame the splits name has a record with `bbox` and `transform_matrix` (the
//! training loss needs both) and an image. Frames group into videos by the `<video>_<frame>`
//! naming rule (`crate::names`).

use std::collections::{BTreeMap, HashSet};
use std::path::{Path, PathBuf};

use gagavatar_flame::{FlameError, TrackedFrame};
use image::RgbImage;
use serde::{Deserialize, Serialize};

use crate::error::{io_err, DataError, Result};
use crate::images::{decode_image, read_image_file};
use crate::names::{group_by_video, sort_frame_names};
use crate::records::{read_records, write_records};
use gagavatar_formats::atomic::write_atomic;
use gagavatar_formats::lmdb::{write_lmdb, LmdbReader};

pub const SPLITS_FILE: &str = "dataset.json";
pub const RELEASE_RECORDS_FILE: &str = "optim.pkl";
pub const RELEASE_IMAGES_DIR: &str = "img_lmdb";
pub const FOLDER_RECORDS_FILE: &str = "records.json";
pub const FOLDER_IMAGES_DIR: &str = "images";

/// `dataset.json`: frame names per split. `val` and `test` may be missing (empty); other keys
/// are ignored.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct DatasetSplits {
    pub train: Vec<String>,
    #[serde(default)]
    pub val: Vec<String>,
    #[serde(default)]
    pub test: Vec<String>,
}

impl DatasetSplits {
    pub fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(io_err(path, "cannot read"))?;
        serde_json::from_str(&text).map_err(|e| DataError::Json {
            path: path.to_owned(),
            reason: e.to_string(),
        })
    }

    /// Writes the splits as JSON, atomically.
    pub fn write(&self, path: &Path) -> Result<()> {
        let mut text = serde_json::to_string_pretty(self).map_err(|e| DataError::Write {
            path: path.to_owned(),
            reason: e.to_string(),
        })?;
        text.push('\n');
        Ok(write_atomic(path, text.as_bytes())?)
    }

    /// `(split name, frame names)` for the three splits.
    pub fn splits(&self) -> [(&'static str, &[String]); 3] {
        [
            ("train", &self.train),
            ("val", &self.val),
            ("test", &self.test),
        ]
    }
}

/// The release layout, opened and checked.
#[derive(Debug)]
pub struct ReleaseDataset {
    dir: PathBuf,
    records: BTreeMap<String, TrackedFrame>,
    images: LmdbReader,
    splits: DatasetSplits,
}

/// Our own layout, opened and checked.
#[derive(Debug)]
pub struct FolderDataset {
    dir: PathBuf,
    records: BTreeMap<String, TrackedFrame>,
    splits: DatasetSplits,
}

/// Either layout.
#[derive(Debug)]
pub enum Dataset {
    Release(ReleaseDataset),
    Folder(FolderDataset),
}

/// Splits from `dir/dataset.json`, or every record in `train` when the file is absent.
fn splits_or_all(dir: &Path, records: &BTreeMap<String, TrackedFrame>) -> Result<DatasetSplits> {
    let path = dir.join(SPLITS_FILE);
    if path.exists() {
        return DatasetSplits::read(&path);
    }
    let mut train: Vec<String> = records.keys().cloned().collect();
    sort_frame_names(&mut train);
    Ok(DatasetSplits {
        train,
        ..DatasetSplits::default()
    })
}

/// Every frame named by the splits has a training-ready record and an image.
fn check_splits(
    dir: &Path,
    records: &BTreeMap<String, TrackedFrame>,
    records_file: &str,
    splits: &DatasetSplits,
    has_image: &dyn Fn(&str) -> bool,
    images_name: &str,
) -> Result<()> {
    let splits_path = dir.join(SPLITS_FILE);
    for (split, names) in splits.splits() {
        for name in names {
            let Some(r) = records.get(name) else {
                return Err(DataError::Layout {
                    path: splits_path,
                    reason: format!(
                        "`{split}` names frame `{name}`, which {records_file} does not hold"
                    ),
                });
            };
            for (field, present) in [
                ("bbox", r.bbox.is_some()),
                ("transform_matrix", r.transform_matrix.is_some()),
            ] {
                if !present {
                    return Err(DataError::Record {
                        path: dir.join(records_file),
                        frame: format!("`{name}`"),
                        field: field.into(),
                        reason: "is missing (training needs it)".into(),
                    });
                }
            }
            if !has_image(name) {
                return Err(DataError::Layout {
                    path: dir.join(images_name),
                    reason: format!("no image for frame `{name}` (named in `{split}`)"),
                });
            }
        }
    }
    Ok(())
}

fn missing_record(path: &Path, name: &str, records: &BTreeMap<String, TrackedFrame>) -> DataError {
    let mut names: Vec<&str> = records.keys().map(String::as_str).collect();
    sort_frame_names(&mut names);
    DataError::MissingKey {
        path: path.to_owned(),
        key: name.to_owned(),
        available: names.iter().take(5).map(|s| s.to_string()).collect(),
        total: records.len(),
    }
}

impl ReleaseDataset {
    pub fn open(dir: &Path) -> Result<Self> {
        let records_path = dir.join(RELEASE_RECORDS_FILE);
        let lmdb_path = dir.join(RELEASE_IMAGES_DIR);
        for p in [&records_path, &lmdb_path] {
            if !p.exists() {
                return Err(DataError::Layout {
                    path: dir.to_owned(),
                    reason: format!(
                        "not a release dataset: {} is missing",
                        p.file_name()
                            .map(|n| n.to_string_lossy())
                            .unwrap_or_default()
                    ),
                });
            }
        }
        let records = read_records(&records_path)?;
        let images = LmdbReader::open(&lmdb_path)?;
        let splits = splits_or_all(dir, &records)?;
        let keys: HashSet<Vec<u8>> = images.keys()?.into_iter().collect();
        check_splits(
            dir,
            &records,
            RELEASE_RECORDS_FILE,
            &splits,
            &|name| keys.contains(name.as_bytes()),
            RELEASE_IMAGES_DIR,
        )?;
        Ok(Self {
            dir: dir.to_owned(),
            records,
            images,
            splits,
        })
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    pub fn records(&self) -> &BTreeMap<String, TrackedFrame> {
        &self.records
    }

    pub fn record(&self, name: &str) -> Result<&TrackedFrame> {
        self.records.get(name).ok_or_else(|| {
            missing_record(&self.dir.join(RELEASE_RECORDS_FILE), name, &self.records)
        })
    }

    /// The frame's image, read from the LMDB and decoded now.
    pub fn image(&self, name: &str) -> Result<RgbImage> {
        match self.images.get(name.as_bytes())? {
            Some(bytes) => decode_image(&bytes, self.images.path(), name),
            None => Err(DataError::Image {
                path: self.images.path().to_owned(),
                key: name.to_owned(),
                reason: "no such entry".into(),
            }),
        }
    }

    pub fn splits(&self) -> &DatasetSplits {
        &self.splits
    }
}

impl FolderDataset {
    pub fn open(dir: &Path) -> Result<Self> {
        let records_path = dir.join(FOLDER_RECORDS_FILE);
        let records = read_records_json(&records_path)?;
        let splits = splits_or_all(dir, &records)?;
        let images = dir.join(FOLDER_IMAGES_DIR);
        check_splits(
            dir,
            &records,
            FOLDER_RECORDS_FILE,
            &splits,
            &|name| image_file(&images, name).is_file(),
            FOLDER_IMAGES_DIR,
        )?;
        Ok(Self {
            dir: dir.to_owned(),
            records,
            splits,
        })
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    pub fn records(&self) -> &BTreeMap<String, TrackedFrame> {
        &self.records
    }

    pub fn record(&self, name: &str) -> Result<&TrackedFrame> {
        self.records
            .get(name)
            .ok_or_else(|| missing_record(&self.dir.join(FOLDER_RECORDS_FILE), name, &self.records))
    }

    pub fn image(&self, name: &str) -> Result<RgbImage> {
        read_image_file(&image_file(&self.dir.join(FOLDER_IMAGES_DIR), name))
    }

    pub fn splits(&self) -> &DatasetSplits {
        &self.splits
    }
}

fn image_file(images: &Path, name: &str) -> PathBuf {
    images.join(format!("{name}.png"))
}

/// `records.json`: `{name: record}`.
pub fn read_records_json(path: &Path) -> Result<BTreeMap<String, TrackedFrame>> {
    let text = std::fs::read_to_string(path).map_err(io_err(path, "cannot read"))?;
    let v: serde_json::Value = serde_json::from_str(&text).map_err(|e| DataError::Json {
        path: path.to_owned(),
        reason: e.to_string(),
    })?;
    let obj = v.as_object().ok_or_else(|| DataError::Json {
        path: path.to_owned(),
        reason: "the top level is not an object {name: record}".into(),
    })?;
    let mut out = BTreeMap::new();
    for (name, rec) in obj {
        let r = TrackedFrame::from_json_value(rec).map_err(|e| {
            let (field, reason) = match e {
                FlameError::Record { field, reason } => (field, reason),
                other => ("<record>".to_owned(), other.to_string()),
            };
            DataError::Record {
                path: path.to_owned(),
                frame: format!("`{name}`"),
                field,
                reason,
            }
        })?;
        out.insert(name.clone(), r);
    }
    Ok(out)
}

impl Dataset {
    /// Opens `dir` in whichever layout it has: `optim.pkl` + `img_lmdb/` (release) or
    /// `records.json` + `images/` (ours).
    pub fn open(dir: &Path) -> Result<Self> {
        if !dir.is_dir() {
            return Err(DataError::Layout {
                path: dir.to_owned(),
                reason: "is not a dataset folder".into(),
            });
        }
        if dir.join(RELEASE_RECORDS_FILE).exists() || dir.join(RELEASE_IMAGES_DIR).exists() {
            return ReleaseDataset::open(dir).map(Dataset::Release);
        }
        if dir.join(FOLDER_RECORDS_FILE).exists() {
            return FolderDataset::open(dir).map(Dataset::Folder);
        }
        Err(DataError::Layout {
            path: dir.to_owned(),
            reason: "not a dataset: expected optim.pkl + img_lmdb/ (release layout) or \
                     records.json + images/ (folder layout)"
                .into(),
        })
    }

    pub fn dir(&self) -> &Path {
        match self {
            Dataset::Release(d) => d.dir(),
            Dataset::Folder(d) => d.dir(),
        }
    }

    pub fn records(&self) -> &BTreeMap<String, TrackedFrame> {
        match self {
            Dataset::Release(d) => d.records(),
            Dataset::Folder(d) => d.records(),
        }
    }

    pub fn record(&self, name: &str) -> Result<&TrackedFrame> {
        match self {
            Dataset::Release(d) => d.record(name),
            Dataset::Folder(d) => d.record(name),
        }
    }

    pub fn image(&self, name: &str) -> Result<RgbImage> {
        match self {
            Dataset::Release(d) => d.image(name),
            Dataset::Folder(d) => d.image(name),
        }
    }

    pub fn splits(&self) -> &DatasetSplits {
        match self {
            Dataset::Release(d) => d.splits(),
            Dataset::Folder(d) => d.splits(),
        }
    }

    /// Every record's frame name, in natural order.
    pub fn names(&self) -> Vec<String> {
        let mut names: Vec<String> = self.records().keys().cloned().collect();
        sort_frame_names(&mut names);
        names
    }

    /// Every record grouped by video, frames in natural order (to group one split, use
    /// `names::group_by_video` on its list).
    pub fn videos(&self) -> BTreeMap<String, Vec<String>> {
        group_by_video(self.records().keys().map(String::as_str))
    }
}

impl ReleaseDataset {
    /// Every record grouped by video, frames in natural order.
    pub fn videos(&self) -> BTreeMap<String, Vec<String>> {
        group_by_video(self.records.keys().map(String::as_str))
    }
}

impl FolderDataset {
    /// Every record grouped by video, frames in natural order.
    pub fn videos(&self) -> BTreeMap<String, Vec<String>> {
        group_by_video(self.records.keys().map(String::as_str))
    }
}

/// Writes a dataset in the release layout into `dir` (created if needed): `img_lmdb/` from
/// `images` (frame name -> encoded PNG / JPEG bytes, e.g. from `images::encode_png`),
/// `optim.pkl` from `records` and `dataset.json` from `splits`. Each part is written
/// atomically; the result is checked by opening it.
pub fn write_release_dataset(
    dir: &Path,
    records: &BTreeMap<String, TrackedFrame>,
    images: impl IntoIterator<Item = (String, Vec<u8>)>,
    splits: &DatasetSplits,
) -> Result<ReleaseDataset> {
    std::fs::create_dir_all(dir).map_err(io_err(dir, "cannot create"))?;
    write_lmdb(
        &dir.join(RELEASE_IMAGES_DIR),
        images.into_iter().map(|(k, v)| (k.into_bytes(), v)),
    )?;
    write_records(&dir.join(RELEASE_RECORDS_FILE), records)?;
    splits.write(&dir.join(SPLITS_FILE))?;
    ReleaseDataset::open(dir)
}
