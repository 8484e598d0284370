//! The book's command-line reference (`docs/src/reference/cli.md`) is generated from the
//! parser (`aggtool help-markdown`, a hidden command using clap-markdown): this test fails when
//! the committed page differs from what this build generates. Regenerate it with
//!
//! ```text
//! AGGTOOL_BLESS=1 cargo test --test cli_reference
//! ```
//!
//! or `cargo run -- help-markdown > docs/src/reference/cli.md`.

mod common;

use std::path::Path;

use common::{aggtool, ok};

#[test]
fn cli_reference_matches_the_parser() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let page = root.join("docs/src/reference/cli.md");
    let generated = ok(&aggtool(&["help-markdown"], root));
    if std::env::var_os("AGGTOOL_BLESS").is_some() {
        std::fs::write(&page, &generated).unwrap();
        return;
    }
    let committed = std::fs::read_to_string(&page).unwrap_or_default();
    assert!(
        committed == generated,
        "{} differs from `aggtool help-markdown`: the command line changed. Regenerate the \
         page with `AGGTOOL_BLESS=1 cargo test --test cli_reference` (or `cargo run -- \
         help-markdown > docs/src/reference/cli.md`) and commit it.",
        page.display()
    );
}

/// Every command's `--help` has an example.
#[test]
fn every_help_has_an_example() {
    let d = tempfile::tempdir().unwrap();
    let commands: &[&[&str]] = &[
        &[],
        &["convert"],
        &["inspect"],
        &["render"],
        &["assemble"],
        &["reference"],
        &["compare"],
        &["gen"],
        &["merge"],
        &["export"],
        &["info"],
        &["flatten"],
        &["demo"],
        &["eval"],
        &["sweep"],
        &["tables"],
        &["tables", "build"],
        &["tables", "check"],
        &["absdf-plot"],
    ];
    for c in commands {
        let mut args = c.to_vec();
        args.push("--help");
        let help = ok(&aggtool(&args, d.path()));
        assert!(help.contains("Example:\n  aggtool "), "{c:?}: {help}");
    }
    // The top-level help documents the exit statuses.
    let help = ok(&aggtool(&["--help"], d.path()));
    for s in [
        "0 success",
        "2 usage error",
        "3 input error",
        "4 output error",
        "130",
    ] {
        assert!(help.contains(s), "{s}: {help}");
    }
}
