//! The five precomputed, scene-independent tables of the factorized ABSDF (paper §3.3, §4,
//! §5.1–§5.3, supplemental §1), generated once by `aggtool tables build`, stored in one
//! versioned binary file (`tables/aggtool-tables.bin`, committed) and embedded in the crate.
//!
//! | table | maps | resolution | used by |
//! |---|---|---|---|
//! | M1 | SGGX (αx, αy) ⊛ SG of sharpness κ → (α+x, α+y, scale) | 20×20×20 | diffuse sampling (§7.3; Eq. 14) |
//! | M2 | roughness beta (mean μ, ν = σ²/(μ(1−μ))) → two GGX lobes (m1, α1, α2) | 32×32 | Eq. 19 |
//! | M3 | SGGX (αx, αy) ⊛ GGX of roughness α → (α+x, α+y, scale) | 50×50×50 | Eq. 20 |
//! | M4 | GGX roughness α → inverse LTC scale (1D) | 256 | S, Eq. 21 |
//! | M5 | GGX roughness α → ∫ D_mic over the sphere (1D) | 256 | S, Eq. 21 |
//!
//! Convolutions use the normalised kernel (the kernel divided by its integral), so that the
//! kernel's mass is a separate factor (∫SG for M1, M5 for M3), and are fitted by
//! `scale · D_sggx(·; R, α+)`: the scale is a third channel beyond the paper's two, because a
//! unit SGGX lobe's mass grows with roughness while convolution with a normalised kernel keeps
//! it (see [`fit::fit_convolution`]). M2 is parameterised by (μ, ν) in [0, 1]² rather than the unbounded beta shape
//! parameters (a, b), which supplemental Eq. 2 relates one to one.
//!
//! Lookups interpolate (multi-)linearly between grid nodes and clamp outside the domain.

pub mod fit;
pub mod ltc;

use std::sync::OnceLock;

/// Format version of the table file; bump when a table's meaning or layout changes.
pub const TABLES_VERSION: u32 = 1;
const MAGIC: &[u8; 8] = b"AGGTABLE";

/// A table over a regular grid on a box domain, with `channels` values per node.
#[derive(Clone, Debug, PartialEq)]
pub struct Table {
    /// The table's name (M1–M5).
    pub name: String,
    /// Nodes per axis.
    pub dims: Vec<u32>,
    /// Domain per axis: (first node, last node).
    pub domain: Vec<(f32, f32)>,
    /// Values per node.
    pub channels: u32,
    /// Node values, the first axis varying fastest, channels innermost.
    pub data: Vec<f32>,
}

impl Table {
    /// A table of zeros with `dims` nodes per axis over `domain`.
    pub fn new(name: &str, dims: &[u32], domain: &[(f32, f32)], channels: u32) -> Self {
        let n: usize = dims.iter().map(|&d| d as usize).product();
        Table {
            name: name.into(),
            dims: dims.to_vec(),
            domain: domain.to_vec(),
            channels,
            data: vec![0.0; n * channels as usize],
        }
    }

    /// Parameter value of node `i` along `axis`.
    pub fn node(&self, axis: usize, i: u32) -> f32 {
        let (a, b) = self.domain[axis];
        let n = self.dims[axis];
        if n <= 1 {
            a
        } else {
            a + (b - a) * i as f32 / (n - 1) as f32
        }
    }

    /// Node coordinates of flat node index `k`.
    pub fn node_params(&self, mut k: usize) -> Vec<f32> {
        let mut p = Vec::with_capacity(self.dims.len());
        for (axis, &d) in self.dims.iter().enumerate() {
            p.push(self.node(axis, (k % d as usize) as u32));
            k /= d as usize;
        }
        p
    }

    /// Number of nodes.
    pub fn node_count(&self) -> usize {
        self.dims.iter().map(|&d| d as usize).product()
    }

    /// Interpolated lookup at `x` (one coordinate per axis), clamped to the domain; writes
    /// `channels` values.
    pub fn lookup_into(&self, x: &[f32], out: &mut [f32]) {
        let c = self.channels as usize;
        let nd = self.dims.len();
        debug_assert!(nd <= 3 && x.len() == nd && out.len() >= c);
        let mut base = [0usize; 3];
        let mut frac = [0f32; 3];
        let mut stride = [0usize; 3];
        let mut s = 1usize;
        for a in 0..nd {
            let (lo, hi) = self.domain[a];
            let n = self.dims[a] as usize;
            let t = if hi > lo && x[a].is_finite() {
                ((x[a] - lo) / (hi - lo)).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let f = t * (n.max(2) - 1) as f32;
            let i = (f as usize).min(n.saturating_sub(2));
            base[a] = i;
            frac[a] = if n > 1 { f - i as f32 } else { 0.0 };
            stride[a] = s;
            s *= n;
        }
        out[..c].iter_mut().for_each(|o| *o = 0.0);
        for corner in 0..(1usize << nd) {
            let mut w = 1.0f32;
            let mut idx = 0usize;
            for a in 0..nd {
                let hi = (corner >> a) & 1 == 1;
                let step = if hi && self.dims[a] > 1 { 1 } else { 0 };
                w *= if hi { frac[a] } else { 1.0 - frac[a] };
                idx += (base[a] + step) * stride[a];
            }
            if w != 0.0 {
                for ch in 0..c {
                    out[ch] += w * self.data[idx * c + ch];
                }
            }
        }
    }

    /// One-channel lookup.
    pub fn lookup1(&self, x: &[f32]) -> f32 {
        let mut o = [0f32; 4];
        self.lookup_into(x, &mut o);
        o[0]
    }
}

/// All five tables, and what is derived from them.
#[derive(Clone, Debug, PartialEq)]
pub struct Tables {
    /// SGGX ⊛ SG of sharpness κ → (α⁺x, α⁺y, scale), for diffuse sampling (§7.3, Eq. 14).
    pub m1: Table,
    /// Roughness beta (μ, ν) → two GGX lobes (m1, α1, α2) (Eq. 19).
    pub m2: Table,
    /// SGGX ⊛ GGX of roughness α → (α⁺x, α⁺y, scale) (Eq. 20).
    pub m3: Table,
    /// GGX roughness α → inverse LTC scale 1/s (S of Eq. 21).
    pub m4: Table,
    /// GGX roughness α → ∫ D_mic over the sphere (Eq. 21).
    pub m5: Table,
    /// S of Eq. 21 tabulated from M4 (not stored: derived on load).
    pub lune: ltc::LuneTable,
}

/// Errors reading a table file.
#[derive(Debug, thiserror::Error)]
pub enum TableError {
    /// The file does not start with the tables' magic bytes.
    #[error("not an aggtool table file (bad magic)")]
    Magic,
    /// The file's version is not this build's.
    #[error("table file version {0} is not supported (this build reads version {TABLES_VERSION})")]
    Version(u32),
    /// The file ends early or holds inconsistent sizes.
    #[error("table file is truncated or malformed: {0}")]
    Malformed(String),
}

struct Reader<'a> {
    b: &'a [u8],
    p: usize,
}

impl Reader<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8], TableError> {
        let end = self
            .p
            .checked_add(n)
            .filter(|&e| e <= self.b.len())
            .ok_or_else(|| TableError::Malformed(format!("need {n} bytes at {}", self.p)))?;
        let s = &self.b[self.p..end];
        self.p = end;
        Ok(s)
    }
    fn u32(&mut self) -> Result<u32, TableError> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().unwrap()))
    }
    fn f32(&mut self) -> Result<f32, TableError> {
        Ok(f32::from_le_bytes(self.take(4)?.try_into().unwrap()))
    }
}

impl Tables {
    /// Serialises: magic, version, count, then per table its name, dims, domain, channels and
    /// data, all little-endian.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::new();
        out.extend_from_slice(MAGIC);
        out.extend(TABLES_VERSION.to_le_bytes());
        let list = [&self.m1, &self.m2, &self.m3, &self.m4, &self.m5];
        out.extend((list.len() as u32).to_le_bytes());
        for t in list {
            out.extend((t.name.len() as u32).to_le_bytes());
            out.extend(t.name.as_bytes());
            out.extend((t.dims.len() as u32).to_le_bytes());
            for (&d, &(a, b)) in t.dims.iter().zip(&t.domain) {
                out.extend(d.to_le_bytes());
                out.extend(a.to_le_bytes());
                out.extend(b.to_le_bytes());
            }
            out.extend(t.channels.to_le_bytes());
            for v in &t.data {
                out.extend(v.to_le_bytes());
            }
        }
        out
    }

    /// Reads the tables from their binary file (`tables/aggtool-tables.bin`'s layout).
    pub fn from_bytes(b: &[u8]) -> Result<Tables, TableError> {
        let mut r = Reader { b, p: 0 };
        if r.take(8).map_err(|_| TableError::Magic)? != MAGIC {
            return Err(TableError::Magic);
        }
        let v = r.u32()?;
        if v != TABLES_VERSION {
            return Err(TableError::Version(v));
        }
        let n = r.u32()?;
        if n != 5 {
            return Err(TableError::Malformed(format!("{n} tables, expected 5")));
        }
        let mut tables = Vec::new();
        for _ in 0..n {
            let len = r.u32()? as usize;
            let name = String::from_utf8(r.take(len)?.to_vec())
                .map_err(|e| TableError::Malformed(e.to_string()))?;
            let nd = r.u32()? as usize;
            if !(1..=3).contains(&nd) {
                return Err(TableError::Malformed(format!("{name}: {nd} dimensions")));
            }
            let mut dims = Vec::new();
            let mut domain = Vec::new();
            for _ in 0..nd {
                dims.push(r.u32()?);
                domain.push((r.f32()?, r.f32()?));
            }
            let channels = r.u32()?;
            let count = dims
                .iter()
                .try_fold(channels as usize, |acc, &d| acc.checked_mul(d as usize))
                .filter(|&c| c > 0 && c <= 1 << 24)
                .ok_or_else(|| TableError::Malformed(format!("{name}: bad size")))?;
            let mut data = Vec::with_capacity(count);
            for _ in 0..count {
                data.push(r.f32()?);
            }
            tables.push(Table {
                name,
                dims,
                domain,
                channels,
                data,
            });
        }
        if r.p != b.len() {
            return Err(TableError::Malformed(format!(
                "{} trailing bytes",
                b.len() - r.p
            )));
        }
        let mut it = tables.into_iter();
        Ok(Tables::new(
            it.next().unwrap(),
            it.next().unwrap(),
            it.next().unwrap(),
            it.next().unwrap(),
            it.next().unwrap(),
        ))
    }

    /// The five tables, with what is derived from them.
    pub fn new(m1: Table, m2: Table, m3: Table, m4: Table, m5: Table) -> Tables {
        let lune = ltc::LuneTable::new(&m4);
        Tables {
            m1,
            m2,
            m3,
            m4,
            m5,
            lune,
        }
    }

    /// The tables embedded in this build.
    pub fn embedded() -> &'static Tables {
        static T: OnceLock<Tables> = OnceLock::new();
        T.get_or_init(|| {
            Tables::from_bytes(EMBEDDED)
                .expect("the embedded table file is valid (checked by tests)")
        })
    }
}

/// The committed table file.
pub const EMBEDDED: &[u8] = include_bytes!("../../tables/aggtool-tables.bin");
