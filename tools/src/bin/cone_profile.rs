//! Where a LoD render's time goes, cone by cone: for a view of an `.agg`, the average number of
//! traversal steps, primitives and weighted hits per cone, and the single-thread time of the
//! walk alone (exact and bound weights), of the walk with every hit shaded, and of `trace` with
//! reservoir shading. The split the closing notes of the runtime issue quote.
//!
//! ```text
//! cargo run --release -p aggtool-tools --bin cone_profile -- FILE.agg VIEW.json [--spp 4]
//! ```

use aggtool_tools as common;

use std::time::Instant;

use aggtool::math::rng::Pcg32;
use aggtool::runtime::{Cone, LodScene, Shading, TraceSettings};
use glam::Vec2;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let agg = args
        .iter()
        .find(|a| a.ends_with(".agg"))
        .ok_or("give FILE.agg")?;
    let view = args
        .iter()
        .find(|a| a.ends_with(".json"))
        .ok_or("give VIEW.json")?;
    let spp = common::flag_u32(&args, "--spp", 4);
    let view = aggtool::render::View::load(std::path::Path::new(view))?;
    let lights = view.lights()?;
    let cam = view.camera();
    let t0 = Instant::now();
    let scene = LodScene::open(std::path::Path::new(agg))?;
    let open = t0.elapsed().as_secs_f64();
    let mut rng = Pcg32::new(1, 1);
    let cones: Vec<Cone> = (0..cam.width * cam.height * spp)
        .map(|i| {
            let px = i / spp;
            let p = Vec2::new((px % cam.width) as f32, (px / cam.width) as f32) + rng.next_2d();
            let (o, d) = cam.ray(p);
            Cone::new(o, d, cam.pixel_angle())
        })
        .collect();
    let n = cones.len() as f64;
    // The first walk prepares the levels: time it apart.
    let t = Instant::now();
    let s = TraceSettings::default();
    for c in &cones {
        let _ = scene.transmittance(c, &s);
    }
    let first = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let (mut steps, mut prims, mut hits, mut inside) = (0u64, 0u64, 0u64, 0u64);
    for c in &cones {
        let mut h = scene.hits(c, &s);
        for _ in &mut h {
            hits += 1;
        }
        steps += h.steps() as u64;
        prims += h.primitives() as u64;
        inside += (h.steps() > 0) as u64;
    }
    let walk_exact = t.elapsed().as_secs_f64();
    let t = Instant::now();
    for c in &cones {
        let _ = scene.transmittance(c, &s);
    }
    let walk_plain = t.elapsed().as_secs_f64();
    let time = |shading: Shading| {
        let s = TraceSettings {
            shading,
            ..Default::default()
        };
        let mut rng = Pcg32::new(2, 2);
        let t = Instant::now();
        let mut acc = 0.0f32;
        for c in &cones {
            acc += scene.trace(c, &lights, &s, &mut rng).radiance.x;
        }
        (t.elapsed().as_secs_f64(), acc)
    };
    // `--only every|reservoir|roulette` times one mode (for instruction counts under callgrind).
    let only = args
        .iter()
        .position(|a| a == "--only")
        .and_then(|i| args.get(i + 1))
        .cloned();
    let run = |name: &str, shading: Shading| {
        if only.as_deref().is_none_or(|o| o == name) {
            time(shading).0
        } else {
            f64::NAN
        }
    };
    let every = run("every", Shading::Every);
    let res1 = run(
        "reservoir",
        Shading::Reservoir {
            picks: 1,
            roulette: false,
        },
    );
    let rr = run(
        "roulette",
        Shading::Reservoir {
            picks: 1,
            roulette: true,
        },
    );
    println!(
        "{agg}: {} cones ({}×{} at {spp}); open {:.1} ms, first walk (levels prepared) {:.3} s",
        cones.len(),
        cam.width,
        cam.height,
        open * 1e3,
        first
    );
    println!(
        "per cone: {:.1} steps ({:.0}% of cones enter the cube), {:.2} primitives, {:.2} hits with weight",
        steps as f64 / n,
        100.0 * inside as f64 / n,
        prims as f64 / n,
        hits as f64 / n
    );
    println!(
        "single thread, ns per cone: walk {:.0}, walk with exact weights {:.0}, trace shading every hit {:.0}, trace reservoir 1 pick {:.0}, with coverage roulette {:.0}",
        walk_plain / n * 1e9,
        walk_exact / n * 1e9,
        every / n * 1e9,
        res1 / n * 1e9,
        rr / n * 1e9
    );
    Ok(())
}
