//! `gagavatar flame ...`: FLAME utilities (synthetic asset, mesh export).

use gagavatar_formats::atomic::write_atomic;
use std::fmt::Write as _;
use std::path::PathBuf;

use clap::Subcommand;
use gagavatar_flame::{synthesize, TrackedFrame};

#[derive(Debug, Subcommand)]
pub enum FlameCmd {
    /// Write the deterministic synthetic FLAME-format asset (release layout and shapes).
    #[command(after_help = "Example:\n  gagavatar flame synth -o flame.safetensors --seed 7")]
    Synth {
        /// Output safetensors file (keys `flame_model.*`, `lmk_embeddings.*`).
        #[arg(short, long)]
        output: PathBuf,
        /// Seed for the blendshapes and pose correctives (the geometry is fixed).
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
    /// Pose a FLAME asset with a tracked-frame record and export the mesh as OBJ.
    #[command(
        after_help = "The record is JSON with `shapecode`, `expcode`, `posecode`, `eyecode` \
(shorter codes are zero-padded, longer ones rejected) and optional `transform_matrix`, `bbox`. \
The OBJ holds the x5-scaled vertices in asset order and 1-based faces.\n\n\
A reduced asset (fewer than 400 shapedirs columns) needs its split: --n-shape N --n-exp M.\n\n\
Example:\n  gagavatar flame mesh --flame FLAME_with_eye.pt --params frame.json -o head.obj"
    )]
    Mesh {
        /// FLAME asset: the release's `.pt` or a `.safetensors` with the same keys.
        #[arg(long)]
        flame: PathBuf,
        /// Tracked-frame record (JSON).
        #[arg(long)]
        params: PathBuf,
        /// Output OBJ file.
        #[arg(short, long)]
        output: PathBuf,
        /// Shape (identity) columns at the start of the asset's `shapedirs`.
        #[arg(long, default_value_t = 300)]
        n_shape: usize,
        /// Expression columns after them; n-shape + n-exp must equal the column count.
        #[arg(long, default_value_t = 100)]
        n_exp: usize,
    },
}

pub fn run(cmd: FlameCmd) -> anyhow::Result<()> {
    match cmd {
        FlameCmd::Synth { output, seed } => {
            let asset = synthesize(seed);
            let bytes = asset.to_safetensors_bytes()?;
            write_atomic(&output, &bytes)?;
            eprintln!(
                "wrote {} ({} vertices, {} faces, seed {seed})",
                output.display(),
                asset.n_vertices,
                asset.n_faces()
            );
            Ok(())
        }
        FlameCmd::Mesh {
            flame,
            params,
            output,
            n_shape,
            n_exp,
        } => {
            let model = crate::cmd_model::load_flame(&flame, n_shape, n_exp)?;
            let record = TrackedFrame::from_json_file(&params)?;
            let out = model.forward(&record.params(&model)?)?;
            let verts = out.vertices.squeeze(0)?.to_vec2::<f32>()?;
            let obj = obj_text(&verts, &model.faces);
            write_atomic(&output, obj.as_bytes())?;
            eprintln!(
                "wrote {} ({} vertices, {} faces)",
                output.display(),
                verts.len(),
                model.faces.len()
            );
            Ok(())
        }
    }
}

fn obj_text(verts: &[Vec<f32>], faces: &[[u32; 3]]) -> String {
    let mut s = String::with_capacity(verts.len() * 40 + faces.len() * 24);
    s.push_str("# gagavatar flame mesh (FLAME vertices x5)\n");
    for v in verts {
        let _ = writeln!(s, "v {} {} {}", v[0], v[1], v[2]);
    }
    for f in faces {
        let _ = writeln!(s, "f {} {} {}", f[0] + 1, f[1] + 1, f[2] + 1);
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mesh_exports_a_reduced_asset_given_its_split() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../crates/flame/tests/golden");
        let dir = std::env::temp_dir().join(format!("gagavatar-flame-mesh-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let params = dir.join("frame.json");
        std::fs::write(
            &params,
            r#"{"shapecode": [0.5, -0.2], "expcode": [0.3], "posecode": [0, 0, 0, 0.2, 0, 0],
                "eyecode": [0, 0.1, 0, 0, 0.1, 0]}"#,
        )
        .unwrap();
        let mesh = |n_shape, n_exp, name: &str| {
            run(FlameCmd::Mesh {
                flame: root.join("tiny_flame.pt"),
                params: params.clone(),
                output: dir.join(name),
                n_shape,
                n_exp,
            })
        };
        // The defaults describe the release's 400 columns, which this 10-column file lacks.
        let err = mesh(300, 100, "default.obj").unwrap_err();
        assert!(format!("{err:#}").contains("--n-shape"), "{err:#}");
        mesh(6, 4, "tiny.obj").unwrap();
        let obj = std::fs::read_to_string(dir.join("tiny.obj")).unwrap();
        assert_eq!(obj.lines().filter(|l| l.starts_with("v ")).count(), 40);
        assert_eq!(obj.lines().filter(|l| l.starts_with("f ")).count(), 60);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
