//! A small PNG for the book from a study's pictures: crop a region, scale it, and keep the
//! palette-friendly 8-bit RGB (the pictures `eval` writes are a few hundred KB wide). Several
//! inputs are cropped alike and laid side by side, in the order given, 2 pixels apart.
//!
//! ```sh
//! cargo run --release -p aggtool-tools --bin png_thumb -- IN.png [IN2.png ...] OUT.png [--crop X,Y,W,H] [--scale 0.5]
//! ```

use anyhow::{bail, Context, Result};

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (mut crop, mut scale, mut files) = (None, 1.0f32, Vec::new());
    let mut it = args.iter();
    while let Some(a) = it.next() {
        match a.as_str() {
            "--crop" => {
                let v: Vec<u32> = it
                    .next()
                    .context("--crop X,Y,W,H")?
                    .split(',')
                    .map(str::parse)
                    .collect::<Result<_, _>>()
                    .context("--crop X,Y,W,H: four integers")?;
                if v.len() != 4 {
                    bail!("--crop X,Y,W,H: four integers");
                }
                crop = Some((v[0], v[1], v[2], v[3]));
            }
            "--scale" => {
                scale = it
                    .next()
                    .context("--scale S")?
                    .parse()
                    .context("--scale S")?;
                if !(scale > 0.0 && scale <= 1.0) {
                    bail!("--scale S: in (0, 1]");
                }
            }
            f => files.push(f.to_string()),
        }
    }
    let Some((output, inputs)) = files.split_last().filter(|(_, i)| !i.is_empty()) else {
        bail!("usage: png_thumb IN.png [IN2.png ...] OUT.png [--crop X,Y,W,H] [--scale S]");
    };
    let mut tiles = Vec::new();
    for input in inputs {
        let mut img = image::open(input)
            .with_context(|| format!("reading {input}"))?
            .to_rgb8();
        if let Some((x, y, w, h)) = crop {
            if x + w > img.width() || y + h > img.height() {
                bail!(
                    "--crop outside the {}×{} picture {input}",
                    img.width(),
                    img.height()
                );
            }
            img = image::imageops::crop_imm(&img, x, y, w, h).to_image();
        }
        tiles.push(img);
    }
    const GAP: u32 = 2;
    let width = tiles.iter().map(|t| t.width()).sum::<u32>() + GAP * (tiles.len() as u32 - 1);
    let height = tiles.iter().map(|t| t.height()).max().unwrap_or(1);
    let mut img = image::RgbImage::from_pixel(width, height, image::Rgb([255, 255, 255]));
    let mut x = 0;
    for t in &tiles {
        image::imageops::replace(&mut img, t, x as i64, 0);
        x += t.width() + GAP;
    }
    let (w, h) = (
        ((img.width() as f32 * scale).round() as u32).max(1),
        ((img.height() as f32 * scale).round() as u32).max(1),
    );
    let out = image::imageops::resize(&img, w, h, image::imageops::FilterType::Triangle);
    out.save(output)
        .with_context(|| format!("writing {output}"))?;
    println!(
        "{output}: {w}×{h}, {} bytes",
        std::fs::metadata(output)?.len()
    );
    Ok(())
}
