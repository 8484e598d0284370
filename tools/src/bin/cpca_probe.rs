//! Feasibility probe: CPCA of the finest level's AIV and ABV tiles of an `.agg`, bytes and
//! errors against the stored maps (no file written).
//!
//! ```text
//! cargo run --release -p aggtool-tools --bin cpca_probe -- IN.agg [CLUSTERS REPS_AIV REPS_ABV TOL]
//! ```
use aggtool::format::Aggregate;
use aggtool::math::cpca::{cpca, CpcaSettings};
use aggtool::math::haar::{forward, quantize_tree, truncate, SparseHaar};

fn dense(t: &SparseHaar) -> Vec<f32> {
    let n = t.n;
    let mut out = Vec::with_capacity((n * n) as usize);
    for y in 0..n {
        for x in 0..n {
            out.push(t.eval(x, y).clamp(0.0, 1.0));
        }
    }
    out
}

fn tree_bytes(tile: &[f32], t: usize, keep: f32, energy: f32) -> usize {
    let (s, mut d) = forward(tile, t);
    truncate(s, &mut d, keep, energy);
    let tree = SparseHaar::new(s, &d, t);
    quantize_tree(&tree).map_or(tree.nodes.len() * 20, |q| q.len() * 6)
}

fn study(name: &str, maps: &[Vec<f32>], n: usize, s: &CpcaSettings, stored_bytes: u64) {
    let t = n / 4;
    let d = t * t;
    let mut bytes = 0usize;
    let mut const_tiles = 0usize;
    let mut sq = 0f64;
    let mut cnt = 0usize;
    let mut reps_total = 0usize;
    let mut clusters_total = 0usize;
    for g in 0..16 {
        let (gx, gy) = (g % 4, g / 4);
        let mut data = Vec::new();
        for m in maps {
            let mut tile = Vec::with_capacity(d);
            for y in 0..t {
                for x in 0..t {
                    tile.push(m[(gy * t + y) * n + gx * t + x]);
                }
            }
            let (lo, hi) = tile
                .iter()
                .fold((f32::MAX, f32::MIN), |(a, b), v| (a.min(*v), b.max(*v)));
            if hi - lo < 2e-3 {
                const_tiles += 1;
                bytes += if lo < 1e-3 || hi > 1.0 - 1e-3 { 1 } else { 2 };
                cnt += d;
                continue;
            }
            data.extend(tile);
        }
        let c = cpca(&data, d, s);
        clusters_total += c.clusters.len();
        for cl in &c.clusters {
            reps_total += cl.reps.len();
            bytes += 8 + 16 * (1 + cl.reps.len());
            bytes += tree_bytes(&cl.mean, t, 1.0, 1.0);
            for u in &cl.reps {
                let r = u.iter().fold(f32::MIN, |a, b| a.max(*b))
                    - u.iter().fold(f32::MAX, |a, b| a.min(*b));
                let scaled: Vec<f32> = u.iter().map(|x| x / r.max(1e-12)).collect();
                bytes += tree_bytes(&scaled, t, 1.0, 1.0);
            }
        }
        // Quantized weights: per rep scale = max |w| / 127.
        let mut scales = vec![Vec::new(); c.clusters.len()];
        for (ci, cl) in c.clusters.iter().enumerate() {
            scales[ci] = vec![0f32; cl.reps.len()];
        }
        for (i, w) in c.weights.iter().enumerate() {
            let ci = c.assign[i] as usize;
            for (j, x) in w.iter().enumerate() {
                scales[ci][j] = scales[ci][j].max(x.abs() / 127.0);
            }
        }
        let m = data.len() / d;
        for i in 0..m {
            let ci = c.assign[i] as usize;
            let cl = &c.clusters[ci];
            bytes += 1 + cl.reps.len();
            let mut rec = cl.mean.clone();
            for (j, u) in cl.reps.iter().enumerate() {
                let st = scales[ci][j];
                let wq = if st > 0.0 {
                    (c.weights[i][j] / st).round() * st
                } else {
                    0.0
                };
                for (o, x) in rec.iter_mut().zip(u) {
                    *o += wq * x;
                }
            }
            for (a, b) in rec.iter().zip(&data[i * d..(i + 1) * d]) {
                sq += ((a.clamp(0.0, 1.0) - b) as f64).powi(2);
            }
            cnt += d;
        }
    }
    println!(
        "{name}: {} maps {n}², stored {} B ({:.1} B/map); CPCA ~{} B ({:.1} B/map, {:.2}x); {} const tiles of {}, {} clusters, {:.2} reps/cluster; RMS error {:.4}",
        maps.len(),
        stored_bytes,
        stored_bytes as f64 / maps.len() as f64,
        bytes,
        bytes as f64 / maps.len() as f64,
        stored_bytes as f64 / bytes as f64,
        const_tiles,
        maps.len() * 16,
        clusters_total,
        reps_total as f64 / clusters_total.max(1) as f64,
        (sq / cnt.max(1) as f64).sqrt()
    );
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let agg = Aggregate::open(std::path::Path::new(&args[1])).expect("open");
    let num = |i: usize, d: f64| args.get(i).and_then(|s| s.parse().ok()).unwrap_or(d);
    let clusters = num(2, 30.0) as usize;
    let reps_aiv = num(3, 10.0) as usize;
    let reps_abv = num(4, 60.0) as usize;
    let tol = num(5, 0.0);
    let lvl = agg.read_level(0);
    let (cb, _) = agg.component_bytes(0);
    let s = agg.settings();
    let aiv: Vec<Vec<f32>> = lvl
        .voxels
        .iter()
        .filter(|v| !v.aiv.is_constant())
        .map(|v| dense(&v.aiv))
        .collect();
    let abv: Vec<Vec<f32>> = lvl
        .faces
        .iter()
        .filter(|f| !f.abv.is_constant())
        .map(|f| dense(&f.abv))
        .collect();
    let t0 = std::time::Instant::now();
    study(
        "AIV",
        &aiv,
        s.aiv_res as usize,
        &CpcaSettings {
            clusters,
            reps: reps_aiv,
            min_per_cluster: 32,
            tolerance: tol,
        },
        cb.aiv_nodes,
    );
    let t1 = std::time::Instant::now();
    study(
        "ABV",
        &abv,
        s.abv_res as usize,
        &CpcaSettings {
            clusters,
            reps: reps_abv,
            min_per_cluster: 32,
            tolerance: tol,
        },
        cb.abv_nodes,
    );
    println!(
        "seconds: AIV {:.1}, ABV {:.1}",
        (t1 - t0).as_secs_f64(),
        t1.elapsed().as_secs_f64()
    );
}
