//! A small PNG for the book from a study's picture: crop a region, scale it, and keep the
//! palette-friendly 8-bit RGB (the pictures `eval` writes are a few hundred KB wide).
//!
//! ```sh
//! cargo run --release -p aggtool-tools --bin png_thumb -- IN.png OUT.png [--crop X,Y,W,H] [--scale 0.5]
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
    let [input, output] = files.as_slice() else {
        bail!("usage: png_thumb IN.png OUT.png [--crop X,Y,W,H] [--scale S]");
    };
    let mut img = image::open(input)
        .with_context(|| format!("reading {input}"))?
        .to_rgb8();
    if let Some((x, y, w, h)) = crop {
        if x + w > img.width() || y + h > img.height() {
            bail!(
                "--crop outside the {}×{} picture",
                img.width(),
                img.height()
            );
        }
        img = image::imageops::crop_imm(&img, x, y, w, h).to_image();
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
