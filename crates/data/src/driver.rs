//! Driving sequences for reenactment and source records.
//!
//! A driving sequence is either
//! * a release tracked folder: `smoothed.pkl` (preferred) or `optim.pkl`, with an optional
//!   `img_lmdb/` holding the driver frames under the same names; frames in natural name
//!   order; the frame rate our tracker recorded in the folder's `track.json` (`"fps"`, the
//!   source video's exact rate), else 25 fps (the release's video rate); a path to the `.pkl`
//!   itself works too;
//! * a JSON file `{"fps": 25, "frames": [record, ...]}`, each record a tracked-frame JSON record
//!   (`TrackedFrame`) that must carry `transform_matrix` (the driving camera), and may carry
//!   `"name"` and `"image"` (a path relative to the JSON file). Either every frame names an
//!   image or none does. Frames keep the file's order; `fps` defaults to 25.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use gagavatar_flame::{FlameError, TrackedFrame};
use image::RgbImage;
use serde_json::Value;

use crate::error::{io_err, DataError, Result};
use crate::images::{decode_image, read_image_file};
use crate::names::frame_name_cmp;
use crate::records::read_records;
use gagavatar_formats::lmdb::LmdbReader;

/// The release's video frame rate, used for pickled sequences (which carry none).
pub const DEFAULT_FPS: f64 = 25.0;
/// The file our tracker writes beside the pickles; its `"fps"` is the source video's rate.
const TRACK_JSON: &str = "track.json";

/// The `"fps"` of a tracked folder's `track.json`: `None` when there is no such file or it
/// records none (a photo, or a folder tracked before the rate was kept); an error when the
/// file is unreadable or the rate is not a positive number.
fn tracked_fps(path: &Path) -> Result<Option<f64>> {
    if !path.is_file() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(path).map_err(io_err(path, "cannot read"))?;
    let json_err = |reason: String| DataError::Json {
        path: path.to_owned(),
        reason,
    };
    let v: Value = serde_json::from_str(&text).map_err(|e| json_err(e.to_string()))?;
    match v.get("fps") {
        None | Some(Value::Null) => Ok(None),
        Some(f) => match f.as_f64() {
            Some(fps) if fps.is_finite() && fps > 0.0 => Ok(Some(fps)),
            _ => Err(json_err(format!(
                "`fps` is {f}, expected a positive number"
            ))),
        },
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct DriverFrame {
    pub name: String,
    pub record: TrackedFrame,
}

#[derive(Debug)]
enum Images {
    None,
    Lmdb(LmdbReader),
    /// One file per frame, in frame order.
    Files(Vec<PathBuf>),
}

#[derive(Debug)]
pub struct DriverSequence {
    /// Where the sequence was read from (the folder, `.pkl` or `.json`).
    pub path: PathBuf,
    pub fps: f64,
    pub frames: Vec<DriverFrame>,
    images: Images,
}

/// `smoothed.pkl`, else `optim.pkl`, in `dir`, in the given preference.
fn tracked_pickle(dir: &Path, prefer: [&str; 2]) -> Result<PathBuf> {
    for name in prefer {
        let p = dir.join(name);
        if p.is_file() {
            return Ok(p);
        }
    }
    Err(DataError::Layout {
        path: dir.to_owned(),
        reason: format!(
            "not a tracked folder: it has neither {} nor {}",
            prefer[0], prefer[1]
        ),
    })
}

fn flame_record_error(path: &Path, frame: String, e: FlameError) -> DataError {
    match e {
        FlameError::Record { field, reason } | FlameError::RecordFile { field, reason, .. } => {
            DataError::Record {
                path: path.to_owned(),
                frame,
                field,
                reason,
            }
        }
        other => DataError::Record {
            path: path.to_owned(),
            frame,
            field: "<record>".into(),
            reason: other.to_string(),
        },
    }
}

impl DriverSequence {
    /// Opens a tracked folder, a `.pkl` of tracked frames, or a JSON sequence.
    pub fn open(path: &Path) -> Result<Self> {
        if path.is_dir() {
            let pkl = tracked_pickle(path, ["smoothed.pkl", "optim.pkl"])?;
            let mut seq = Self::from_pickle(path, &pkl, path)?;
            if let Some(fps) = tracked_fps(&path.join(TRACK_JSON))? {
                seq.fps = fps;
            }
            return Ok(seq);
        }
        let ext = path
            .extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase())
            .unwrap_or_default();
        match ext.as_str() {
            "pkl" | "pickle" => {
                let dir = path.parent().unwrap_or(Path::new("."));
                Self::from_pickle(path, path, dir)
            }
            "json" => Self::from_json(path),
            _ if !path.exists() => Err(io_err(path, "cannot open")(std::io::Error::from(
                std::io::ErrorKind::NotFound,
            ))),
            _ => Err(DataError::Layout {
                path: path.to_owned(),
                reason: "expected a tracked folder, a .pkl or a .json driving sequence".into(),
            }),
        }
    }

    /// `path` is what the user named; images come from `lmdb_dir/img_lmdb` when present.
    fn from_pickle(path: &Path, pkl: &Path, lmdb_dir: &Path) -> Result<Self> {
        let records = read_records(pkl)?;
        let frames = ordered_frames(records);
        if frames.is_empty() {
            return Err(DataError::Layout {
                path: pkl.to_owned(),
                reason: "holds no frames".into(),
            });
        }
        let images = match open_optional_lmdb(lmdb_dir)? {
            Some(env) => Images::Lmdb(env),
            None => Images::None,
        };
        Ok(Self {
            path: path.to_owned(),
            fps: DEFAULT_FPS,
            frames,
            images,
        })
    }

    fn from_json(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(io_err(path, "cannot read"))?;
        let json_err = |reason: String| DataError::Json {
            path: path.to_owned(),
            reason,
        };
        let v: Value = serde_json::from_str(&text).map_err(|e| json_err(e.to_string()))?;
        let obj = v.as_object().ok_or_else(|| {
            json_err("the top level is not an object {\"fps\", \"frames\"}".into())
        })?;
        let fps = match obj.get("fps") {
            None | Some(Value::Null) => DEFAULT_FPS,
            Some(f) => match f.as_f64() {
                Some(x) if x.is_finite() && x > 0.0 => x,
                _ => {
                    return Err(json_err(format!(
                        "`fps` is {f}, expected a positive number"
                    )))
                }
            },
        };
        let list = match obj.get("frames") {
            Some(Value::Array(a)) => a,
            Some(_) => return Err(json_err("`frames` is not a list".into())),
            None => return Err(json_err("`frames` is missing".into())),
        };
        if list.is_empty() {
            return Err(json_err("`frames` is empty".into()));
        }
        let base = path.parent().unwrap_or(Path::new("."));
        let mut frames = Vec::with_capacity(list.len());
        let mut files: Vec<Option<PathBuf>> = Vec::with_capacity(list.len());
        for (i, item) in list.iter().enumerate() {
            let name = match item.get("name") {
                None | Some(Value::Null) => format!("{i:06}"),
                Some(Value::String(s)) => s.clone(),
                Some(other) => {
                    return Err(DataError::Record {
                        path: path.to_owned(),
                        frame: format!("#{i}"),
                        field: "name".into(),
                        reason: format!("is {other}, expected a string"),
                    })
                }
            };
            let label = if item.get("name").is_some_and(Value::is_string) {
                format!("#{i} (`{name}`)")
            } else {
                format!("#{i}")
            };
            let record = TrackedFrame::from_json_value(item)
                .map_err(|e| flame_record_error(path, label.clone(), e))?;
            if record.transform_matrix.is_none() {
                return Err(DataError::Record {
                    path: path.to_owned(),
                    frame: label,
                    field: "transform_matrix".into(),
                    reason: "is missing (a driving frame needs its camera)".into(),
                });
            }
            files.push(match item.get("image") {
                None | Some(Value::Null) => None,
                Some(Value::String(rel)) => Some(base.join(rel)),
                Some(other) => {
                    return Err(DataError::Record {
                        path: path.to_owned(),
                        frame: label,
                        field: "image".into(),
                        reason: format!("is {other}, expected a relative path"),
                    })
                }
            });
            frames.push(DriverFrame { name, record });
        }
        let with_image = files.iter().filter(|f| f.is_some()).count();
        if with_image != 0 && with_image != files.len() {
            let i = files.iter().position(Option::is_none).unwrap_or(0);
            return Err(DataError::Record {
                path: path.to_owned(),
                frame: format!("#{i}"),
                field: "image".into(),
                reason: "is missing while other frames have one (give all or none)".into(),
            });
        }
        let files: Vec<PathBuf> = files.into_iter().flatten().collect();
        let images = if files.is_empty() {
            Images::None
        } else {
            Images::Files(files)
        };
        Ok(Self {
            path: path.to_owned(),
            fps,
            frames,
            images,
        })
    }

    pub fn len(&self) -> usize {
        self.frames.len()
    }

    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Whether the sequence comes with driver images (`image` then gives every frame's).
    pub fn has_images(&self) -> bool {
        !matches!(self.images, Images::None)
    }

    /// The driver image of frame `i`, read and decoded now; `None` without images.
    pub fn image(&self, i: usize) -> Result<Option<RgbImage>> {
        let frame = self.frames.get(i).ok_or_else(|| DataError::Layout {
            path: self.path.clone(),
            reason: format!(
                "frame index {i} is out of range ({} frames)",
                self.frames.len()
            ),
        })?;
        match &self.images {
            Images::None => Ok(None),
            Images::Files(files) => read_image_file(&files[i]).map(Some),
            Images::Lmdb(env) => match env.get(frame.name.as_bytes())? {
                Some(bytes) => decode_image(&bytes, env.path(), &frame.name).map(Some),
                None => Err(DataError::Image {
                    path: env.path().to_owned(),
                    key: frame.name.clone(),
                    reason: "no such entry in img_lmdb".into(),
                }),
            },
        }
    }
}

fn ordered_frames(records: BTreeMap<String, TrackedFrame>) -> Vec<DriverFrame> {
    let mut frames: Vec<DriverFrame> = records
        .into_iter()
        .map(|(name, record)| DriverFrame { name, record })
        .collect();
    frames.sort_by(|a, b| frame_name_cmp(&a.name, &b.name));
    frames
}

/// `dir/img_lmdb` if present.
pub(crate) fn open_optional_lmdb(dir: &Path) -> Result<Option<LmdbReader>> {
    let p = dir.join("img_lmdb");
    if p.exists() {
        Ok(Some(LmdbReader::open(&p)?))
    } else {
        Ok(None)
    }
}

/// The first bytes of a file (enough to tell what it is).
fn read_head(path: &Path) -> Result<Vec<u8>> {
    use std::io::Read;
    let mut head = Vec::with_capacity(64);
    std::fs::File::open(path)
        .and_then(|f| f.take(64).read_to_end(&mut head))
        .map_err(io_err(path, "cannot read"))?;
    Ok(head)
}

/// How many available names an error lists.
const SHOWN_KEYS: usize = 5;

/// The source record: a JSON record file, or a frame of a release pickle (`optim.pkl` /
/// `smoothed.pkl`, or a tracked folder, where `optim.pkl` is preferred) named by `key`. The
/// kind is read from the file's first bytes; a file that is neither (a photo given by mistake)
/// is refused with what it is.
pub fn read_source_record(path: &Path, key: Option<&str>) -> Result<TrackedFrame> {
    let pkl = if path.is_dir() {
        tracked_pickle(path, ["optim.pkl", "smoothed.pkl"])?
    } else {
        let head = read_head(path)?;
        let is_pickle = head.first() == Some(&0x80);
        if let (Some(kind), false) = (gagavatar_formats::sniff::describe(&head), is_pickle) {
            return Err(DataError::Layout {
                path: path.to_owned(),
                reason: format!(
                    "this is {kind}, not a tracking record: give a tracked-frame JSON record \
                     (shapecode, expcode, posecode, eyecode, transform_matrix) or a tracker's \
                     optim.pkl with --source-key"
                ),
            });
        }
        let json_like = head
            .iter()
            .find(|b| !b.is_ascii_whitespace())
            .is_some_and(|&b| b == b'{');
        let is_json_name = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("json"));
        if json_like || (is_json_name && !is_pickle) {
            return TrackedFrame::from_json_file(path).map_err(|e| match e {
                FlameError::Io { err, .. } => io_err(path, "cannot read")(err),
                other => flame_record_error(path, "(source record)".into(), other),
            });
        }
        path.to_owned()
    };
    let mut records = read_records(&pkl)?;
    let mut names: Vec<&String> = records.keys().collect();
    names.sort_by(|a, b| frame_name_cmp(a, b));
    let available: Vec<String> = names
        .iter()
        .take(SHOWN_KEYS)
        .map(|s| s.to_string())
        .collect();
    let total = records.len();
    let Some(key) = key else {
        return Err(DataError::Layout {
            path: pkl,
            reason: format!(
                "holds {total} frames: name one with --source-key (e.g. {})",
                available.join(", ")
            ),
        });
    };
    records.remove(key).ok_or_else(|| DataError::MissingKey {
        path: pkl.clone(),
        key: key.to_owned(),
        available,
        total,
    })
}
