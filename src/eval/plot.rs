//! Plots: the ABSDF's Fig. 4 slices for `aggtool absdf` ([`plot_slices`]) and the Pareto plots
//! for `aggtool sweep`: error against a cost, one point per setting, the presets
//! marked, the Pareto front drawn; and line plots ([`line_plot`], the fly-through's bias per
//! frame). Shapes and lines are drawn by the `plotters` crate on its
//! bitmap backend (plotters.rs docs: `BitMapBackend::with_buffer`, `ChartBuilder`,
//! `ChartContext::backend_coord`); text by our own 5×7 font ([`crate::render::label`]), which
//! keeps plotters' font stack (font-kit or ab_glyph and a font file) out of the build.

use std::path::Path;

use anyhow::{anyhow, Result};
use glam::{Vec2, Vec3};
use plotters::prelude::*;

use crate::absdf::cases::{case_samples, sphere_grid};
use crate::absdf::estimate::{estimate, EstimateSettings};
use crate::absdf::{ground_truth, Absdf};
use crate::bsdf::Bsdf;
use crate::film::{write_rgb8_png, Image};
use crate::render::label::{draw_text, line_height, text_width};
use crate::scene::SurfaceParams;
use crate::tables::Tables;

/// One point of a plot.
#[derive(Clone, Debug)]
pub struct Point {
    /// The cost (x).
    pub x: f64,
    /// The error (y).
    pub y: f64,
    /// Written beside the point.
    pub label: String,
    /// Drawn as a square in the preset colour (a circle otherwise).
    pub marked: bool,
    /// Another method for comparison (the sweep's mesh of equal bytes): a green diamond, left
    /// out of the Pareto front, with its own legend entry when any point is one.
    pub other: bool,
}

/// Which points lie on the Pareto front of lower `y` at lower `x`: those that no other point
/// dominates (at most its x and at most its y, one of them strictly). Non-finite points are
/// never on it.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<bool> {
    points
        .iter()
        .map(|&(x, y)| {
            x.is_finite()
                && y.is_finite()
                && !points
                    .iter()
                    .any(|&(u, v)| u <= x && v <= y && (u < x || v < y))
        })
        .collect()
}

/// Round tick values covering `lo..hi`: steps of 1, 2 or 5 times a power of ten, about
/// `count` of them.
fn linear_ticks(lo: f64, hi: f64, count: usize) -> Vec<f64> {
    let span = (hi - lo).max(1e-12);
    let raw = span / count.max(1) as f64;
    let p = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * p)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * p);
    // Integer multiples of the step, so that errors do not accumulate.
    let first = (lo / step).ceil() as i64;
    (first..)
        .map(|k| k as f64 * step)
        .take_while(|t| *t <= hi + 1e-9 * span)
        .collect()
}

/// A tick's text: few digits, no trailing zeros.
fn tick_text(v: f64) -> String {
    let s = if v != 0.0 && (v.abs() >= 1e4 || v.abs() < 1e-3) {
        format!("{v:.1e}")
    } else {
        format!("{v:.4}")
    };
    if s.contains('.') && !s.contains('e') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

/// A text to draw once plotters has let go of the pixel buffer: (x, y, text, scale, colour).
type Label = (i32, i32, String, u32, [u8; 3]);

/// The chart type both plots draw on.
type Chart<'a, 'b> = ChartContext<
    'a,
    BitMapBackend<'b>,
    plotters::coord::cartesian::Cartesian2d<
        plotters::coord::types::RangedCoordf64,
        plotters::coord::types::RangedCoordf64,
    >,
>;

/// A plot's size and margins, and what every plot draws around its data: the frame with grid
/// lines at the ticks, the tick labels, the title and the axes' names.
struct Frame {
    w: u32,
    h: u32,
    left: u32,
    right: u32,
    top: u32,
    bottom: u32,
}

impl Frame {
    /// The chart over `x0..x1` × `y0..y1` inside the margins of `root`, with a light grid line at
    /// each tick and the frame drawn.
    fn chart<'a, 'b>(
        &self,
        root: &'a DrawingArea<BitMapBackend<'b>, plotters::coord::Shift>,
        (x0, x1, y0, y1): (f64, f64, f64, f64),
        x_ticks: &[(f64, String)],
        y_ticks: &[(f64, String)],
        path: &Path,
    ) -> Result<Chart<'a, 'b>> {
        let err = |e: &dyn std::fmt::Display| anyhow!("plotting {}: {e}", path.display());
        let mut chart = ChartBuilder::on(root)
            .margin_left(self.left)
            .margin_right(self.right)
            .margin_top(self.top)
            .margin_bottom(self.bottom)
            .build_cartesian_2d(x0..x1, y0..y1)
            .map_err(|e| err(&e))?;
        let light = RGBColor(225, 225, 225);
        let grid = x_ticks
            .iter()
            .map(|(x, _)| vec![(*x, y0), (*x, y1)])
            .chain(y_ticks.iter().map(|(y, _)| vec![(x0, *y), (x1, *y)]));
        chart
            .draw_series(grid.map(|p| PathElement::new(p, light)))
            .map_err(|e| err(&e))?;
        chart
            .draw_series(std::iter::once(Rectangle::new(
                [(x0, y0), (x1, y1)],
                BLACK.stroke_width(1),
            )))
            .map_err(|e| err(&e))?;
        Ok(chart)
    }

    /// The tick labels, below the frame and left of it.
    fn tick_labels(
        chart: &Chart,
        (x0, y0): (f64, f64),
        x_ticks: &[(f64, String)],
        y_ticks: &[(f64, String)],
        labels: &mut Vec<Label>,
    ) {
        for (x, t) in x_ticks {
            let (px, py) = chart.backend_coord(&(*x, y0));
            let tw = text_width(t, 1) as i32;
            labels.push((px - tw / 2, py + 6, t.clone(), 1, [0, 0, 0]));
        }
        for (y, t) in y_ticks {
            let (px, py) = chart.backend_coord(&(x0, *y));
            let tw = text_width(t, 1) as i32;
            labels.push((px - tw - 6, py - 3, t.clone(), 1, [0, 0, 0]));
        }
    }

    /// Adds the title (at twice the size where it fits) and the axes' names to `labels`, draws
    /// every label into `rgb` and writes the PNG (atomically).
    fn finish(
        &self,
        path: &Path,
        rgb: &mut [u8],
        mut labels: Vec<Label>,
        title: &str,
        x_label: &str,
        y_label: &str,
    ) -> Result<()> {
        let (w, h) = (self.w, self.h);
        let ts = if text_width(title, 2) + self.left < w {
            2
        } else {
            1
        };
        labels.push((self.left as i32, 16, title.to_string(), ts, [0, 0, 0]));
        let plot_mid = (self.left + (w - self.left - self.right) / 2) as i32;
        labels.push((
            plot_mid - text_width(x_label, 2) as i32 / 2,
            (h - self.bottom + 24) as i32,
            x_label.to_string(),
            2,
            [0, 0, 0],
        ));
        labels.push((8, self.top as i32 - 18, y_label.to_string(), 2, [0, 0, 0]));
        for (x, y, t, scale, c) in labels {
            if x >= 0 && y >= 0 && y + (line_height(scale) as i32) <= h as i32 {
                draw_text(rgb, w, h, x as u32, y as u32, &t, scale, c);
            }
        }
        write_rgb8_png(path, w, h, rgb)?;
        Ok(())
    }
}

/// Writes a scatter plot of `points` (x: `x_label`, y: `y_label`) with the Pareto front as a
/// line and each point labelled, as a PNG (atomically). The x axis is logarithmic when the
/// costs span more than a factor of 20.
pub fn pareto_plot(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    points: &[Point],
) -> Result<()> {
    let frame = Frame {
        w: 960,
        h: 640,
        left: 90,
        right: 150,
        top: 50,
        bottom: 60,
    };
    let (w, h, right, top) = (frame.w, frame.h, frame.right, frame.top);
    let finite: Vec<&Point> = points
        .iter()
        .filter(|p| p.x.is_finite() && p.y.is_finite())
        .collect();
    let (xmin, xmax) = finite
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.x), b.max(p.x)));
    let (ymin, ymax) = finite
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.y), b.max(p.y)));
    let log_x = !finite.is_empty() && xmin > 0.0 && xmax / xmin > 20.0;
    let tx = |x: f64| if log_x { x.log10() } else { x };
    let pad = |lo: f64, hi: f64| {
        let s = if hi > lo { hi - lo } else { hi.abs().max(1e-3) };
        (lo - 0.08 * s, hi + 0.08 * s)
    };
    let (x0, x1) = if finite.is_empty() {
        (0.0, 1.0)
    } else {
        pad(tx(xmin), tx(xmax))
    };
    let (y0, y1) = if finite.is_empty() {
        (0.0, 1.0)
    } else {
        let (a, b) = pad(ymin, ymax);
        (a.max(0.0), b)
    };
    // The front of the plotted method's points (others never dominate them).
    let front = pareto_front(
        &points
            .iter()
            .map(|p| {
                if p.other {
                    (f64::NAN, f64::NAN)
                } else {
                    (p.x, p.y)
                }
            })
            .collect::<Vec<_>>(),
    );
    let green = RGBColor(30, 150, 70);
    let preset = RGBColor(200, 60, 40);
    let varied = RGBColor(40, 90, 200);
    let grey = RGBColor(150, 150, 150);
    let err = |e: &dyn std::fmt::Display| anyhow!("plotting {}: {e}", path.display());
    let mut rgb = vec![255u8; (w * h * 3) as usize];
    let mut texts: Vec<Label> = Vec::new();
    let x_ticks: Vec<(f64, String)> = if log_x {
        let (a, b) = (x0.floor() as i32, x1.ceil() as i32);
        (a..=b)
            .flat_map(|k| [1.0, 2.0, 5.0].map(|m| m * 10f64.powi(k)))
            .filter(|v| (x0..=x1).contains(&v.log10()))
            .map(|v| (v.log10(), tick_text(v)))
            .collect()
    } else {
        linear_ticks(x0, x1, 6)
            .into_iter()
            .map(|v| (v, tick_text(v)))
            .collect()
    };
    let y_ticks: Vec<(f64, String)> = linear_ticks(y0, y1, 6)
        .into_iter()
        .map(|v| (v, tick_text(v)))
        .collect();
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
        let mut chart = frame.chart(&root, (x0, x1, y0, y1), &x_ticks, &y_ticks, path)?;
        // The Pareto front, left to right.
        let mut fp: Vec<(f64, f64)> = points
            .iter()
            .zip(&front)
            .filter(|(_, f)| **f)
            .map(|(p, _)| (tx(p.x), p.y))
            .collect();
        fp.sort_by(|a, b| a.0.total_cmp(&b.0));
        chart
            .draw_series(LineSeries::new(fp, grey.stroke_width(2)))
            .map_err(|e| err(&e))?;
        // Points: squares for presets, circles otherwise.
        let mut spots: Vec<(i32, i32)> = Vec::new();
        for p in &finite {
            let at = (tx(p.x), p.y);
            if p.other {
                chart
                    .draw_series(std::iter::once(
                        EmptyElement::at(at)
                            + Polygon::new(vec![(0, -6), (6, 0), (0, 6), (-6, 0)], green.filled()),
                    ))
                    .map_err(|e| err(&e))?;
            } else if p.marked {
                chart
                    .draw_series(std::iter::once(
                        EmptyElement::at(at) + Rectangle::new([(-5, -5), (5, 5)], preset.filled()),
                    ))
                    .map_err(|e| err(&e))?;
            } else {
                chart
                    .draw_series(std::iter::once(Circle::new(at, 5, varied.filled())))
                    .map_err(|e| err(&e))?;
            }
            // Labels of points that land on the same spot stack downwards.
            let (px, py) = chart.backend_coord(&at);
            let k = spots
                .iter()
                .filter(|(x, y)| (x - px).abs() <= 3 && (y - py).abs() <= 3)
                .count() as i32;
            spots.push((px, py));
            let c = if p.other {
                [20, 110, 50]
            } else if p.marked {
                [150, 40, 25]
            } else {
                [25, 60, 150]
            };
            let dy = k * line_height(1) as i32;
            texts.push((px + 8, py - 4 + dy, p.label.clone(), 1, c));
        }
        Frame::tick_labels(&chart, (x0, y0), &x_ticks, &y_ticks, &mut texts);
        // Legend, right of the plot.
        let lx = (w - right + 14) as i32;
        let ly = top as i32 + 10;
        root.draw(&Rectangle::new(
            [(lx, ly), (lx + 10, ly + 10)],
            preset.filled(),
        ))
        .map_err(|e| err(&e))?;
        root.draw(&Circle::new((lx + 5, ly + 30), 5, varied.filled()))
            .map_err(|e| err(&e))?;
        root.draw(&PathElement::new(
            vec![(lx, ly + 55), (lx + 12, ly + 55)],
            grey.stroke_width(2),
        ))
        .map_err(|e| err(&e))?;
        texts.push((lx + 18, ly + 2, "preset".into(), 1, [0, 0, 0]));
        texts.push((lx + 18, ly + 27, "one setting".into(), 1, [0, 0, 0]));
        texts.push((lx + 18, ly + 36, "varied".into(), 1, [0, 0, 0]));
        texts.push((lx + 18, ly + 52, "pareto front".into(), 1, [0, 0, 0]));
        if finite.iter().any(|p| p.other) {
            root.draw(&Polygon::new(
                vec![
                    (lx + 5, ly + 69),
                    (lx + 11, ly + 75),
                    (lx + 5, ly + 81),
                    (lx - 1, ly + 75),
                ],
                green.filled(),
            ))
            .map_err(|e| err(&e))?;
            texts.push((lx + 18, ly + 66, "mesh of equal".into(), 1, [0, 0, 0]));
            texts.push((lx + 18, ly + 75, "bytes".into(), 1, [0, 0, 0]));
        }
        root.present().map_err(|e| err(&e))?;
    }
    let xl = format!("{x_label}{}", if log_x { " (log scale)" } else { "" });
    frame.finish(path, &mut rgb, texts, title, &xl, y_label)
}

/// One line of a [`line_plot`]: its name in the legend, its colour, its points (x, y), drawn
/// left to right in the order given; a non-finite point breaks the line there.
#[derive(Clone, Debug)]
pub struct Series {
    /// Written in the legend.
    pub name: String,
    /// The line's colour (sRGB).
    pub color: [u8; 3],
    /// The points.
    pub points: Vec<(f64, f64)>,
}

/// Writes a line plot of `series` (x: `x_label`, y: `y_label`) with a legend, as a PNG
/// (atomically): the fly-through's bias per frame, one line per method. Both axes are linear
/// and span the finite points.
pub fn line_plot(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[Series],
) -> Result<()> {
    let frame = Frame {
        w: 960,
        h: 480,
        left: 90,
        right: 190,
        top: 50,
        bottom: 60,
    };
    let (w, h) = (frame.w, frame.h);
    let finite = || {
        series
            .iter()
            .flat_map(|s| s.points.iter())
            .filter(|(x, y)| x.is_finite() && y.is_finite())
    };
    let span = |v: &mut dyn Iterator<Item = f64>| {
        let (lo, hi) = v.fold((f64::MAX, f64::MIN), |(a, b), x| (a.min(x), b.max(x)));
        if lo > hi {
            (0.0, 1.0)
        } else {
            let s = if hi > lo { hi - lo } else { hi.abs().max(1e-3) };
            (lo - 0.05 * s, hi + 0.05 * s)
        }
    };
    let (x0, x1) = span(&mut finite().map(|p| p.0));
    let (y0, y1) = span(&mut finite().map(|p| p.1));
    let err = |e: &dyn std::fmt::Display| anyhow!("plotting {}: {e}", path.display());
    let mut rgb = vec![255u8; (w * h * 3) as usize];
    let mut texts: Vec<Label> = Vec::new();
    let ticks = |lo: f64, hi: f64, n: usize| -> Vec<(f64, String)> {
        linear_ticks(lo, hi, n)
            .into_iter()
            .map(|v| (v, tick_text(v)))
            .collect()
    };
    let (x_ticks, y_ticks) = (ticks(x0, x1, 8), ticks(y0, y1, 6));
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
        let mut chart = frame.chart(&root, (x0, x1, y0, y1), &x_ticks, &y_ticks, path)?;
        let lx = (w - frame.right + 14) as i32;
        for (i, s) in series.iter().enumerate() {
            let c = RGBColor(s.color[0], s.color[1], s.color[2]);
            // Runs of finite points, each its own line.
            for run in s
                .points
                .split(|(x, y)| !(x.is_finite() && y.is_finite()))
                .filter(|r| !r.is_empty())
            {
                chart
                    .draw_series(LineSeries::new(run.iter().copied(), c.stroke_width(2)))
                    .map_err(|e| err(&e))?;
            }
            let ly = frame.top as i32 + 10 + 20 * i as i32;
            root.draw(&PathElement::new(
                vec![(lx, ly + 4), (lx + 14, ly + 4)],
                c.stroke_width(2),
            ))
            .map_err(|e| err(&e))?;
            texts.push((lx + 20, ly, s.name.clone(), 1, [0, 0, 0]));
        }
        Frame::tick_labels(&chart, (x0, y0), &x_ticks, &y_ticks, &mut texts);
        root.present().map_err(|e| err(&e))?;
    }
    frame.finish(path, &mut rgb, texts, title, x_label, y_label)
}

/// Fig. 4 style plot: for 8×8 incident directions (equal-area grid), the outgoing lat-long slice
/// (`w × w/2` pixels) of f̂; returns linear RGB (width 8w, height 4w) for the ground truth and
/// for the factored model.
pub fn plot_slices(name: &str, tables: &Tables, samples: u32, w: u32) -> Option<(Image, Image)> {
    let s = case_samples(name, samples)?;
    let app = estimate(&s, &EstimateSettings::default())?;
    let absdf = Absdf::new(&app, tables);
    let gt_samples: Vec<(Vec3, SurfaceParams, f32)> =
        s.iter().map(|x| (x.normal, x.params, x.weight)).collect();
    let h = w / 2;
    let mut gt = Image::new(8 * w, 8 * h);
    let mut ours = Image::new(8 * w, 8 * h);
    let incident = sphere_grid(8);
    for (k, &wi) in incident.iter().enumerate() {
        let (ox, oy) = ((k as u32 % 8) * w, (k as u32 / 8) * h);
        for y in 0..h {
            for x in 0..w {
                let wo = crate::math::spherical::equirect_to_dir(Vec2::new(
                    (x as f32 + 0.5) / w as f32,
                    (y as f32 + 0.5) / h as f32,
                ));
                let idx = ((oy + y) * 8 * w + ox + x) as usize;
                gt.pixels[idx] = ground_truth(&gt_samples, wi, wo);
                ours.pixels[idx] = absdf.eval(wi, wo);
            }
        }
    }
    Some((gt, ours))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pareto_front_keeps_undominated_points() {
        // (1, 3) and (2, 1) trade off; (3, 2) is dominated by (2, 1); (2, 1) twice are both on
        // it; NaN never is.
        let f = pareto_front(&[
            (1.0, 3.0),
            (2.0, 1.0),
            (3.0, 2.0),
            (2.0, 1.0),
            (f64::NAN, 0.0),
        ]);
        assert_eq!(f, [true, true, false, true, false]);
    }

    #[test]
    fn ticks_are_round_and_cover_the_range() {
        // Within rounding (0.6 is 3 × 0.2 in binary); the text rounds to 4 digits.
        let t = linear_ticks(0.0, 1.0, 5);
        let want = [0.0, 0.2, 0.4, 0.6, 0.8, 1.0];
        assert!(
            t.len() == 6 && t.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-12),
            "{t:?}"
        );
        assert_eq!(tick_text(t[3]), "0.6");
        let t = linear_ticks(0.0213, 0.0377, 6);
        assert!(
            t.len() >= 3 && t.iter().all(|v| (0.0213..=0.0377).contains(v)),
            "{t:?}"
        );
        assert_eq!(tick_text(0.25), "0.25");
        assert_eq!(tick_text(12.0), "12");
    }

    /// A plot is a PNG of the stated size with coloured points on it; one point, equal
    /// points and a wide range of costs (log axis) all draw.
    #[test]
    fn plot_writes_a_png() {
        let dir = tempfile::tempdir().unwrap();
        let pts = |xs: &[f64]| -> Vec<Point> {
            xs.iter()
                .enumerate()
                .map(|(i, &x)| Point {
                    x,
                    y: 0.01 * (i + 1) as f64,
                    label: format!("p{i}"),
                    marked: i == 0,
                    other: i == 2,
                })
                .collect()
        };
        for (k, xs) in [vec![1.0], vec![1.0, 1.0], vec![0.5, 3.0, 200.0]]
            .iter()
            .enumerate()
        {
            let path = dir.path().join(format!("p{k}.png"));
            pareto_plot(&path, "title", "bake seconds", "rmse", &pts(xs)).unwrap();
            let img = ::image::open(&path).unwrap().to_rgb8();
            assert_eq!(img.dimensions(), (960, 640));
            assert!(
                img.pixels().any(|p| p.0 == [200, 60, 40]),
                "preset square drawn"
            );
        }
    }

    /// A line plot is a PNG of the stated size with each series' colour on it; a NaN point
    /// breaks a line instead of failing, and a single point or no point still draws.
    #[test]
    fn line_plot_draws_each_series() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("l.png");
        let series = vec![
            Series {
                name: "a".into(),
                color: [200, 60, 40],
                points: vec![(0.0, 0.01), (1.0, f64::NAN), (2.0, 0.03), (3.0, 0.02)],
            },
            Series {
                name: "b".into(),
                color: [40, 90, 200],
                points: vec![(0.0, -0.01), (3.0, 0.0)],
            },
        ];
        line_plot(&path, "title", "level", "e", &series).unwrap();
        let img = ::image::open(&path).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (960, 480));
        for c in [[200, 60, 40], [40, 90, 200]] {
            assert!(img.pixels().any(|p| p.0 == c), "{c:?} drawn");
        }
        for pts in [vec![], vec![(1.0, 1.0)]] {
            let one = vec![Series {
                name: "c".into(),
                color: [30, 150, 70],
                points: pts,
            }];
            line_plot(&path, "title", "x", "y", &one).unwrap();
        }
    }
}
