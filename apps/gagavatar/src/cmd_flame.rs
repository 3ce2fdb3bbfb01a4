//! `gagavatar flame ...`: FLAME utilities (synthetic asset, mesh export).

use clap::Subcommand;

#[derive(Debug, Subcommand)]
pub enum FlameCmd {}

pub fn run(cmd: FlameCmd) -> anyhow::Result<()> {
    match cmd {}
}
