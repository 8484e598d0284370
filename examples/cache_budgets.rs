//! Renders an aggregate or an assembly manifest under several block-cache budgets, each as a
//! whole `aggtool render` command, and prints per budget the wall and CPU time, the peak
//! resident memory of the command, the cache's own figures (blocks loaded and evicted, peak
//! bytes) and whether the image's bits match the default budget's.
//!
//! ```text
//! cargo build --release
//! cargo run --release --example cache_budgets -- FILE.agg|MANIFEST.json VIEW.json \
//!     [--budgets 16,64,256] [--spp N]
//! ```

mod common;

use std::path::PathBuf;
use std::process::Command;

use aggtool::util::process::measure;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let (input, view) =
        match (args.get(1), args.get(2)) {
            (Some(a), Some(v)) => (a.clone(), v.clone()),
            _ => return Err(
                "usage: cache_budgets FILE.agg|MANIFEST.json VIEW.json [--budgets 16,64] [--spp N]"
                    .into(),
            ),
        };
    let value = |flag: &str| common::flag_value(&args, flag);
    let budgets: Vec<Option<u64>> = std::iter::once(None)
        .chain(
            value("--budgets")
                .unwrap_or_else(|| "16,64,256".into())
                .split(',')
                .filter_map(|b| b.trim().parse().ok())
                .map(Some),
        )
        .collect();
    // The aggtool binary of this build, beside the examples' folder.
    let exe = std::env::current_exe()?;
    let bin = exe
        .parent()
        .and_then(|p| p.parent())
        .map(|p| p.join("aggtool"))
        .filter(|p| p.exists())
        .ok_or("build the aggtool binary first (cargo build --release)")?;
    let dir = tempfile_dir()?;
    println!("| budget | wall s | CPU s | peak RSS | cache: loaded | evicted | peak | same bits |");
    println!("|---|---|---|---|---|---|---|---|");
    // Pixels as bits (the EXR's bytes may differ: its chunks are compressed in parallel).
    let mut first: Option<Vec<u32>> = None;
    for b in budgets {
        let out = dir.join(format!(
            "{}.exr",
            b.map_or("default".into(), |b| b.to_string())
        ));
        let mut cmd = Command::new(&bin);
        cmd.args(["render", &input, "--view", &view, "-o"])
            .arg(&out);
        if let Some(spp) = value("--spp") {
            cmd.args(["--spp", &spp]);
        }
        if let Some(b) = b {
            cmd.args(["--cache-mib", &b.to_string()]);
        }
        let m = measure(&mut cmd)?;
        if !m.success {
            return Err(format!("aggtool render failed: {}", m.stderr).into());
        }
        let cache = m
            .stdout
            .lines()
            .find(|l| l.starts_with("stats: cache:"))
            .unwrap_or("")
            .to_string();
        // "stats: cache: N blocks loaded, M evicted, peak X MiB of a Y MiB budget (...)".
        let number_before = |word: &str| {
            cache
                .split(',')
                .find(|p| p.contains(word))
                .and_then(|p| p.split_whitespace().rev().nth(word.split(' ').count()))
                .unwrap_or("?")
                .to_string()
        };
        let peak = cache
            .split("peak ")
            .nth(1)
            .and_then(|p| p.split(" of").next())
            .unwrap_or("?")
            .to_string();
        let img = aggtool::film::Image::read_exr(&out)?;
        let bytes: Vec<u32> = img
            .pixels
            .iter()
            .flat_map(|p| p.to_array())
            .map(f32::to_bits)
            .collect();
        let same = match &first {
            None => {
                first = Some(bytes);
                "(reference)".to_string()
            }
            Some(f) => (f == &bytes).to_string(),
        };
        println!(
            "| {} | {:.2} | {:.2} | {:.1} MiB | {} | {} | {} | {} |",
            b.map_or("default".into(), |b| format!("{b} MiB")),
            m.wall,
            m.cpu,
            m.max_rss as f64 / (1 << 20) as f64,
            number_before("blocks loaded"),
            number_before("evicted"),
            peak,
            same
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

/// A fresh folder under the system's temporary folder.
fn tempfile_dir() -> std::io::Result<PathBuf> {
    let d = std::env::temp_dir().join(format!("aggtool-cache-budgets-{}", std::process::id()));
    std::fs::create_dir_all(&d)?;
    Ok(d)
}
