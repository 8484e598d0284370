//! The quality study (`aggtool eval`, `aggtool::eval::study_scene`): bakes kept in an
//! `agg_dir` are reused as they are, and `normalize: false` reaches the LoD methods.

use aggtool::bake::BakeSettings;
use aggtool::eval::{study_scene, SceneResult, StudySettings};

mod common;

fn ours(r: &[SceneResult]) -> f64 {
    r[0].methods
        .iter()
        .find(|m| m.method == "ours")
        .expect("an 'ours' row")
        .rmse
}

#[test]
fn study_reuses_kept_bakes_and_renders_unnormalised_on_request() {
    let dir = tempfile::tempdir().unwrap();
    let kept = dir.path().join("bakes");
    std::fs::create_dir_all(&kept).unwrap();
    let scene = common::gen_scene("lattice", 3000);
    let settings = StudySettings {
        resolutions: vec![8],
        spp: 8,
        reference_spp: 64,
        bake: BakeSettings {
            max_res: 8,
            min_res: 4,
            samples: 8,
            aiv_res: 8,
            aiv_rays: 8,
            abv_res: 8,
            abv_full_res: 8,
            ..Default::default()
        },
        agg_dir: Some(kept.clone()),
        normalize: true,
        image: None,
        samples_per_walk: 0,
    };
    let run = |s: &StudySettings, out: &str| {
        study_scene(
            "lattice",
            &scene,
            s,
            &dir.path().join(out),
            &aggtool::util::no_progress,
        )
        .unwrap()
    };
    let first = run(&settings, "a");
    let agg = kept.join("lattice-8.agg");
    assert!(agg.exists(), "the bake is kept as NAME-RES.agg");
    let stamp = std::fs::metadata(&agg).unwrap().modified().unwrap();
    let second = run(&settings, "b");
    assert_eq!(
        std::fs::metadata(&agg).unwrap().modified().unwrap(),
        stamp,
        "a kept bake is reused, not baked again"
    );
    assert_eq!(ours(&first), ours(&second), "same bake, same seeds");
    let plain = run(
        &StudySettings {
            normalize: false,
            ..settings.clone()
        },
        "c",
    );
    let (a, b) = (ours(&first), ours(&plain));
    assert!(a.is_finite() && b.is_finite() && a > 0.0 && b > 0.0);
    assert_ne!(a, b, "normalize: false renders the LoD unnormalised");
    // The finest level at twice the pixels (`eval --image`): the same bake, a 16² picture,
    // and the medians' table names the size.
    let large = run(
        &StudySettings {
            image: Some(16),
            ..settings.clone()
        },
        "d",
    );
    assert_eq!((large[0].res, large[0].image), (8, 16));
    assert!(large[0].picture.ends_with("lattice-8-16px.png"));
    let png = image::open(&large[0].picture).unwrap();
    assert!(png.width() >= 16 * 3, "the picture holds 16² renders");
    let table = aggtool::eval::summary_table(&[first[0].clone(), large[0].clone()]);
    let ratio = |r: &SceneResult| {
        let m = |n: &str| r.methods.iter().find(|m| m.method == n).unwrap().rmse;
        m("ours") / m("ref@spp")
    };
    assert!(
        table.contains(&format!("| 8³ | 1 | {:.2} |", ratio(&first[0]))),
        "{table}"
    );
    assert!(
        table.contains(&format!("| 8³ at 16² | 1 | {:.2} |", ratio(&large[0]))),
        "{table}"
    );
}
