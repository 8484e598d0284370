//! What a prepared voxel costs in memory, by part: the runtime's records, the inflated block
//! bytes they read, and the ABSDF built for a voxel shaded (runtime issue, deliverable 2:
//! "resident at most twice the inflated stored bytes").
//!
//! ```text
//! cargo run --release -p aggtool-tools --bin resident_probe -- FILE.agg [LEVEL...]
//! ```
//!
//! Per level (default: the finest): voxels, bytes stored and inflated per voxel, the
//! inflated bytes by component, and the mean ABSDF by part over every voxel (the runtime
//! builds one only for a voxel a cone shades).

use std::path::Path;

use aggtool::format::Aggregate;
use aggtool::tables::Tables;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let path = args
        .first()
        .ok_or_else(|| anyhow::anyhow!("usage: resident_probe FILE.agg [LEVEL...]"))?;
    let agg = Aggregate::open(Path::new(path))?;
    let mut levels: Vec<usize> = args[1..].iter().filter_map(|a| a.parse().ok()).collect();
    if levels.is_empty() {
        levels.push(0);
    }
    let tables = Tables::embedded();
    for l in levels {
        let (stored, inflated) = agg.stored_and_inflated_bytes(l);
        let (c, quantized) = agg.component_bytes(l);
        let mut n = 0usize;
        let mut parts = [0usize; 4];
        let mut names = [""; 4];
        let (mut in_place, mut metal) = (0usize, 0usize);
        let mut lobes_hist = [0usize; 5];
        for v in agg.voxels(l) {
            n += 1;
            lobes_hist[v.lobes().count().min(4)] += 1;
            // As the runtime builds it: the moments read in place where the block allows.
            if let Some(h) = v.moment_halves() {
                in_place += 1;
                metal += h.metal as usize;
            }
            let a = v.absdf(tables);
            for (k, (name, b)) in a.memory_parts().into_iter().enumerate() {
                parts[k] += b;
                names[k] = name;
            }
        }
        let per = |b: u64| b as f64 / n.max(1) as f64;
        println!("level {l}: {n} voxels, quantized {quantized}");
        println!(
            "  stored {:.0} B/voxel, inflated {:.0} B/voxel (voxel blocks and face blocks)",
            per(stored),
            per(inflated)
        );
        println!(
            "  inflated by component, B/voxel: keys {:.0}, voxels {:.0}, lobes {:.0}, moments {:.0}+{:.0}, aiv {:.0}, faces {:.0}, abv {:.0}, exposure {:.0}",
            per(c.keys),
            per(c.voxels),
            per(c.lobes),
            per(c.moments),
            per(c.dielectric_moments),
            per(c.aiv_nodes),
            per(c.faces),
            per(c.abv_nodes),
            per(c.exposure)
        );
        let total: usize = parts.iter().sum();
        print!("  ABSDF {:.0} B/voxel:", total as f64 / n.max(1) as f64);
        for k in 0..parts.len() {
            print!(" {} {:.0}", names[k], parts[k] as f64 / n.max(1) as f64);
        }
        println!();
        println!("  lobes per voxel (0..4): {:?}", lobes_hist);
        println!("  moments read in place: {in_place} voxels ({metal} metal)");
    }
    Ok(())
}
