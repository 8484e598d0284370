//! The committed header `include/aggtool.h` is what cbindgen generates from `src/lib.rs`
//! (the CI check, as for the FlatBuffers code). `AGG_BLESS=1` rewrites it.

use std::path::Path;

#[test]
fn header_matches_a_fresh_generation() {
    let crate_dir = Path::new(env!("CARGO_MANIFEST_DIR"));
    let config = cbindgen::Config::from_file(crate_dir.join("cbindgen.toml")).unwrap();
    let mut fresh = Vec::new();
    cbindgen::Builder::new()
        .with_crate(crate_dir)
        .with_config(config)
        .generate()
        .expect("cbindgen generates the header")
        .write(&mut fresh);
    let path = crate_dir.join("include/aggtool.h");
    if std::env::var_os("AGG_BLESS").is_some() {
        std::fs::write(&path, &fresh).unwrap();
        return;
    }
    let committed = std::fs::read(&path).unwrap_or_default();
    assert!(
        committed == fresh,
        "{} is stale: regenerate with AGG_BLESS=1 cargo test -p aggtool-capi --test header",
        path.display()
    );
}
