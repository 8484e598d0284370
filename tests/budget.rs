//! The error budget by oracle substitution (`aggtool eval --budget`, `aggtool::eval::budget`):
//! its "baked" row is the runtime's estimator, and with every oracle on it reaches the
//! reference far closer than the baked model does.

use aggtool::bake::BakeSettings;
use aggtool::eval::budget::{budget_scene, BudgetSettings, Oracles};

mod common;

/// The lattice's budget at 16³ (small bakes and few samples: a test's budget), its rows as
/// baked or normalised.
fn lattice_budget(normalize: bool) -> aggtool::eval::budget::BudgetResult {
    lattice_budget_at(normalize, None, Vec::new())
}

/// [`lattice_budget`] rendered at `image`² pixels (`eval --budget --image`).
fn lattice_budget_at(
    normalize: bool,
    image: Option<u32>,
    abv_parts: Vec<u8>,
) -> aggtool::eval::budget::BudgetResult {
    let dir = tempfile::tempdir().unwrap();
    let scene = common::gen_scene("lattice", 3000);
    let settings = BudgetSettings {
        res: 16,
        image,
        spp: 16,
        reference_spp: 256,
        samples: 16,
        bake: BakeSettings {
            max_res: 16,
            min_res: 8,
            samples: 16,
            aiv_res: 8,
            aiv_rays: 8,
            abv_res: 8,
            abv_full_res: 8,
            ..Default::default()
        },
        normalize,
        abv_cells: if abv_parts.is_empty() {
            Vec::new()
        } else {
            vec![8]
        },
        abv_parts,
    };
    let agg = dir.path().join("lattice-16.agg");
    let r = budget_scene(
        "lattice",
        &scene,
        &agg,
        &settings,
        dir.path(),
        &aggtool::util::no_progress,
    )
    .unwrap();
    println!(
        "{}",
        aggtool::eval::budget::budget_table(std::slice::from_ref(&r))
    );
    assert!(r.picture.exists());
    r
}

/// Every row finite, and the "baked" row the runtime's estimator on the traversal layer,
/// drawing the same random numbers: its first render (seed 1) is the runtime's image (as
/// baked or normalised, as the rows are) but for the order of floating-point sums; the row's
/// RMSE is that of the mean of two seeds, so compare it with the runtime's at a tolerance of
/// the noise's size.
fn check_rows(r: &aggtool::eval::budget::BudgetResult) {
    for x in &r.rows {
        assert!(
            x.rmse.is_finite() && x.bias.is_finite(),
            "{}: {x:?}",
            x.term
        );
    }
    let baked = r
        .rows
        .iter()
        .find(|x| x.oracles == Oracles::default())
        .unwrap();
    assert!(
        (baked.rmse - r.runtime_rmse).abs() < 0.5 * r.runtime_rmse,
        "baked row {} against the runtime's {}",
        baked.rmse,
        r.runtime_rmse
    );
}

#[test]
fn budget_rows_agree_with_the_runtime_and_all_oracles_close_the_gap() {
    let r = lattice_budget(false);
    let row = |o: Oracles| r.rows.iter().find(|x| x.oracles == o).unwrap();
    let (baked, all) = (row(Oracles::default()), row(Oracles::ALL));
    check_rows(&r);
    // Every approximation replaced: the bias left (the voxels' spatial averaging) is well
    // under the baked model's (measured 0.0094 against 0.0283 at 32³).
    assert!(
        all.bias < 0.6 * baked.bias,
        "all oracles: bias {} against the baked {}",
        all.bias,
        baked.bias
    );
    assert!(
        (all.mean_ratio - 1.0).abs() < 0.05,
        "all: mean {}",
        all.mean_ratio
    );
}

/// With the rows normalised (the default, as the runtime renders): the "baked" row is the
/// runtime's normalised estimator, the candidate-fix row is gone (it is the baked one), and
/// every oracle but the crossing count (which needs no normalising) still closes most of the
/// gap.
#[test]
fn normalised_budget_rows_agree_with_the_normalised_runtime() {
    let r = lattice_budget(true);
    assert!(r.normalized);
    assert!(
        r.rows.iter().all(|x| !x.oracles.normalize),
        "no candidate-fix row"
    );
    let row = |o: Oracles| r.rows.iter().find(|x| x.oracles == o).unwrap();
    let baked = row(Oracles::default());
    let no_coverage = row(Oracles {
        coverage: false,
        ..Oracles::ALL
    });
    check_rows(&r);
    assert!(
        (baked.rmse - r.runtime_default_rmse[1]).abs() < 0.5 * r.runtime_default_rmse[1],
        "baked row {} against the runtime's default normalised render {}",
        baked.rmse,
        r.runtime_default_rmse[1]
    );
    assert!(
        no_coverage.bias < 0.8 * baked.bias,
        "all but coverage: bias {} against the baked {}",
        no_coverage.bias,
        baked.bias
    );
}

/// The budget of the 16³ level at 32² pixels (`eval --budget --image 32`, two pixels a voxel,
/// as the fidelity study's 128³ at 256²): the result and the picture say the size, every row
/// is finite, and with every term exact the bias falls below the baked one's.
#[test]
fn budget_at_a_larger_image() {
    let r = lattice_budget_at(true, Some(32), Vec::new());
    assert_eq!((r.res, r.image), (16, 32));
    assert!(
        r.picture.ends_with("lattice-budget-16-32px.png"),
        "{:?}",
        r.picture
    );
    let row = |o: Oracles| r.rows.iter().find(|x| x.oracles == o).unwrap();
    let (baked, all) = (row(Oracles::default()), row(Oracles::ALL));
    assert!(r
        .rows
        .iter()
        .all(|x| x.rmse.is_finite() && x.bias.is_finite()));
    assert!(
        all.bias < baked.bias,
        "all exact {} against baked {}",
        all.bias,
        baked.bias
    );
}

/// The ABV's rows (`eval --budget --abv-parts 1,2 --abv-cells 8`): the baked model, the exact
/// ABV, all and all but the ABV, the ABV over the 8² map's cells, over the face's reachable
/// points, and over the whole face and its quarters, alone and with the rest exact; every row
/// finite, and the ABV's sub-face oracles with the rest exact closer to "all" than "all but
/// the ABV" is (the ray's own direction and a smaller part of the face than the baked map).
#[test]
fn abv_rows_split_the_baked_map() {
    let r = lattice_budget_at(true, None, vec![1, 2]);
    let names: Vec<&str> = r.rows.iter().map(|x| x.term.as_str()).collect();
    assert_eq!(
        names,
        [
            "baked",
            "ABV (Eq. 26)",
            "all",
            "all but ABV",
            "ABV over the face, directions over the 8² cell",
            "ABV over the face's reachable points",
            "ABV over the face",
            "all, ABV over the face",
            "ABV over 1/2 × 1/2 of the face",
            "all, ABV over 1/2 × 1/2 of the face",
        ]
    );
    check_rows(&r);
    let bias = |name: &str| r.rows.iter().find(|x| x.term == name).unwrap().bias;
    println!(
        "all {} / all but ABV {} / all, ABV over 1/2 {}",
        bias("all"),
        bias("all but ABV"),
        bias("all, ABV over 1/2 × 1/2 of the face")
    );
    assert!(
        bias("all, ABV over 1/2 × 1/2 of the face") < bias("all but ABV"),
        "{:?}",
        r.rows
    );
}
