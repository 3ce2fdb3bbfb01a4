//! AFL++ driver: `GAGAVATAR_FUZZ_TARGET=<name>` picks the harness (names in
//! `gagavatar_fuzz::TARGETS`). See `fuzz/README.md` for the commands.

fn main() {
    let name = std::env::var("GAGAVATAR_FUZZ_TARGET").unwrap_or_default();
    let Some(f) = gagavatar_fuzz::target(&name) else {
        let names: Vec<&str> = gagavatar_fuzz::TARGETS.iter().map(|(n, _)| *n).collect();
        eprintln!("set GAGAVATAR_FUZZ_TARGET to one of: {}", names.join(", "));
        std::process::exit(2);
    };
    afl::fuzz!(|data: &[u8]| {
        f(data);
    });
}
