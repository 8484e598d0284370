//! How much of the LoD's error at equal spp is noise and how much is bias, per shading
//! strategy: on the quality study's view of an asset (`aggtool eval`'s sun and sky, res² pixels),
//! the reference at `--reference-spp` is the truth; the reference at `--spp` and the LoD under
//! each strategy are rendered twice (seeds 1 and 2), so that noise variance = ½·mean((a − b)²)
//! and bias = √(MSE − noise variance), as the error budget splits them; the image's mean against
//! the truth's tells a global darkening from local error. CPU seconds are the
//! render loops' own (user + system, all threads).
//!
//! ```text
//! cargo run --release -p aggtool-tools --bin shading_noise -- ASSET.glb ASSET.agg [--res 64] [--spp 64] [--reference-spp 1024] [--no-normalize]
//! ```

use aggtool_tools as common;

use aggtool::film::Image;
use aggtool::render::compare::compare;
use aggtool::render::reference::{self, ReferenceSettings};
use aggtool::runtime::{LodScene, Shading, TraceSettings};
use aggtool::trace::Accel;
use aggtool::util::{cpu_seconds, no_progress};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (Some(asset), Some(agg)) = (
        args.iter()
            .find(|a| !a.starts_with("--") && !a.ends_with(".agg")),
        args.iter().find(|a| a.ends_with(".agg")),
    ) else {
        return Err("give ASSET and FILE.agg".into());
    };
    let res = common::flag_u32(&args, "--res", 64);
    let spp = common::flag_u32(&args, "--spp", 64);
    let ref_spp = common::flag_u32(&args, "--reference-spp", 1024);
    let scene = aggtool::import::load(std::path::Path::new(asset), Default::default())?;
    let accel = Accel::build(&scene);
    let view = aggtool::eval::study_view(&scene, res, spp);
    let camera = view.camera();
    let lights = view.lights()?;
    let reference = |spp: u32, seed: u64| -> Image {
        reference::render(
            &accel,
            &camera,
            &lights,
            ReferenceSettings { spp, seed },
            &no_progress,
        )
        .0
    };
    let truth = reference(ref_spp, 7);
    let rmse = |a: &Image, b: &Image| compare(a, b).expect("same size").rmse;
    let row = |name: &str, a: Image, b: Image, seconds: f64| {
        let mse = 0.5 * (rmse(&a, &truth).powi(2) + rmse(&b, &truth).powi(2));
        let noise = 0.5 * rmse(&a, &b).powi(2);
        let mean = |i: &Image| i.mean().dot(glam::Vec3::splat(1.0 / 3.0));
        println!(
            "| {name} | {:.4} | {:.4} | {:.4} | {:+.1}% | {:.3} |",
            mse.sqrt(),
            noise.sqrt(),
            (mse - noise).max(0.0).sqrt(),
            100.0 * (0.5 * (mean(&a) + mean(&b)) / mean(&truth) - 1.0),
            seconds
        );
    };
    println!("{asset} at {res}² pixels, {spp} spp, against {ref_spp} spp");
    println!("| method | RMSE | noise | bias | mean vs truth | cpu s per render |");
    println!("|---|---|---|---|---|---|");
    let c = cpu_seconds();
    let (a, b) = (reference(spp, 1), reference(spp, 2));
    row("reference", a, b, (cpu_seconds() - c) / 2.0);
    let lod = LodScene::open(std::path::Path::new(agg))?;
    let reservoir = |picks, roulette| Shading::Reservoir { picks, roulette };
    let strategies: [(&str, Shading, u32); 6] = [
        ("every hit", Shading::Every, 1),
        ("reservoir 1 (default)", Shading::default(), 1),
        ("reservoir 1 + roulette", reservoir(1, true), 1),
        ("reservoir 2", reservoir(2, false), 1),
        ("reservoir 1, nee 2", Shading::default(), 2),
        ("every hit, nee 2", Shading::Every, 2),
    ];
    // Prepare the levels once so that no row pays for them.
    let _ = aggtool::runtime::render(
        &lod,
        &camera,
        &lights,
        1,
        9,
        &TraceSettings::default(),
        &no_progress,
    );
    for (name, shading, nee) in strategies {
        let settings = TraceSettings {
            shading,
            nee,
            normalize: !args.iter().any(|a| a == "--no-normalize"),
            ..Default::default()
        };
        let c = cpu_seconds();
        let img = |seed| {
            aggtool::runtime::render(&lod, &camera, &lights, spp, seed, &settings, &no_progress).0
        };
        let (a, b) = (img(1), img(2));
        row(name, a, b, (cpu_seconds() - c) / 2.0);
    }
    Ok(())
}
