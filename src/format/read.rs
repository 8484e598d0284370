//! Reading `.agg` files: map the file, verify the header and the index, and read zero-copy.
//!
//! Opening is cheap and lazy: [`Aggregate::open_lazy`] maps the file and checks the header
//! (identifier, major version, checksum, size: truncated and trailing data are told apart) and
//! the index (checksum, FlatBuffers structure, settings, levels, and that every blob it names
//! is in range, aligned and overlaps no other). Each block is verified the first time it is
//! read (its CRC-32, the FlatBuffers verifier, the invariants the accessors rely on: sorted
//! keys, ranges inside their arrays, well-shaped wavelet trees, finite numbers, and zero padding
//! up to the next blob), once, thread-safely; a block that fails is refused with an error and
//! never read. [`Aggregate::open`] verifies every block up front, as tools and tests want. After
//! verification accessors index without further checks that could fail, and no user file can
//! make them panic.

use std::fs::File;
use std::ops::Range;
use std::path::Path;
use std::sync::OnceLock;

use glam::{Mat3, UVec3, Vec2, Vec3};

use super::encode::{ComponentBytes, Counts};
use super::level::{FaceData, LevelData, VoxelData};
use super::settings::RecordedSettings;
use super::{fb, FormatError, Header, ALIGN, BLOCK_ID, HEADER_SIZE, INDEX_ID};
use crate::absdf::{MaterialMoments, MomentHalves, Moments, NdfLobe, VoxelAppearance};
use crate::math::frame::Frame;
use crate::math::haar::{
    dequantize_tree, eval_tree, validate_tree, Node, QNode, SparseHaar, Q_DETAIL,
};
use crate::math::sphere_maps::{
    concentric_hemisphere_to_square, equal_area_sphere_to_square, grid_cell,
};
use crate::spatial::{demorton3, face_normal, morton3, Ellipsoid, Face, Grid, UVec3Key};

enum Backing {
    Map(memmap2::Mmap),
    Owned(Vec<u8>),
}

/// What a blob of the index holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum BlobKind {
    Voxels(u32),
    Faces(u32),
    Reserved,
}

/// A blob the index names, and whether it has been verified.
struct Blob {
    offset: u64,
    size: u64,
    first_key: u64,
    last_key: u64,
    count: u32,
    crc32: u32,
    kind: BlobKind,
    /// Where the next blob (or the index) starts: the bytes in between must be zero.
    gap_end: u64,
    /// Verified: `Some(bytes)` for a compressed blob (format 1.5), the FlatBuffer it inflated
    /// to, kept for the aggregate's life; `None` for a blob read in place from the file.
    checked: OnceLock<Result<Option<Box<[u8]>>, String>>,
    /// The verdict of [`Aggregate::load_block`]'s verification, which keeps no bytes: a block
    /// loaded again after a cache evicted it is inflated again but not verified again.
    verdict: OnceLock<Result<(), String>>,
}

/// A level's grid, counts and blobs.
struct LevelInfo {
    grid: Grid,
    counts: Counts,
    voxel_blobs: Range<usize>,
    face_blobs: Range<usize>,
}

/// An opened aggregate: the header and index verified; blocks verified on first use (all of
/// them up front for [`Aggregate::open`]).
pub struct Aggregate {
    data: Backing,
    header: Header,
    checksums: bool,
    /// Whether block verification walks the visibility trees' shapes (see `open_lazy`).
    trees: bool,
    settings: RecordedSettings,
    levels: Vec<LevelInfo>,
    blobs: Vec<Blob>,
}

fn corrupt(s: impl Into<String>) -> FormatError {
    FormatError::Corrupt(s.into())
}

pub(crate) fn g(v: &fb::Vec3f) -> Vec3 {
    Vec3::new(v.x(), v.y(), v.z())
}

fn finite3(v: &fb::Vec3f) -> bool {
    g(v).is_finite()
}

fn node(n: &fb::HaarNode) -> Node {
    Node {
        details: [n.h(), n.v(), n.d()],
        children: n.children(),
        subtree: n.subtree(),
    }
}

fn qnode(n: &fb::QHaarNode) -> QNode {
    QNode {
        q: [n.h(), n.v(), n.d()],
        links: n.links(),
    }
}

/// Bytes of one `HaarNode` struct (schema: three floats, a uint, a ubyte, padding).
const NODE_BYTES: usize = 20;
/// Bytes of one `QHaarNode` struct (1.4: the links, three bytes, a pad byte).
const QNODE_BYTES: usize = 6;

/// A block's tree nodes, in the float layout (1.0–1.3, and 1.4 `--lossless`) or the
/// fixed-point one (1.4).
#[derive(Clone, Copy)]
enum Nodes<'a> {
    F32(flatbuffers::Vector<'a, fb::HaarNode>),
    Q16(flatbuffers::Vector<'a, fb::QHaarNode>),
}

impl<'a> Nodes<'a> {
    /// The AIV nodes of a verified voxel block.
    fn aiv(b: &fb::Block<'a>) -> Nodes<'a> {
        match b.aiv_qnodes() {
            Some(q) => Nodes::Q16(q),
            None => Nodes::F32(b.aiv_nodes().expect("verified")),
        }
    }

    /// The ABV nodes of a verified face block.
    fn abv(b: &fb::Block<'a>) -> Nodes<'a> {
        match b.abv_qnodes() {
            Some(q) => Nodes::Q16(q),
            None => Nodes::F32(b.abv_nodes().expect("verified")),
        }
    }

    fn len(&self) -> usize {
        match self {
            Nodes::F32(v) => v.len(),
            Nodes::Q16(v) => v.len(),
        }
    }

    /// Node `i`'s structure and (for the float layout) details: what [`validate_tree`] checks.
    fn shape(&self, i: usize) -> Node {
        match self {
            Nodes::F32(v) => node(v.get(i)),
            Nodes::Q16(v) => qnode(v.get(i)).node(1),
        }
    }

    /// The nodes `start..start + count` of a tree as raw bytes (verified to lie inside the
    /// vector).
    #[inline]
    fn tree(&self, start: usize, count: usize) -> Tree<'a> {
        let (b, w) = match self {
            Nodes::F32(v) => (v.bytes(), NODE_BYTES),
            Nodes::Q16(v) => (v.bytes(), QNODE_BYTES),
        };
        let bytes = b.get(start * w..(start + count) * w).unwrap_or(&[]);
        match self {
            Nodes::F32(_) => Tree::F32(bytes),
            Nodes::Q16(_) => Tree::Q16(bytes),
        }
    }

    /// The tree `start..start + count` of an `n × n` map, decoded.
    fn decode(&self, n: u32, scaling: f32, start: usize, count: usize) -> SparseHaar {
        match self {
            Nodes::F32(v) => SparseHaar {
                n,
                scaling,
                nodes: (start..start + count).map(|i| node(v.get(i))).collect(),
            },
            Nodes::Q16(v) => {
                let q: Vec<QNode> = (start..start + count).map(|i| qnode(v.get(i))).collect();
                dequantize_tree(n, scaling, &q)
            }
        }
    }
}

/// One tree's raw node bytes, in either layout.
#[derive(Clone, Copy)]
enum Tree<'a> {
    F32(&'a [u8]),
    Q16(&'a [u8]),
}

/// A voxel's AIV map (`n` × `n` cells of the equal-area square) as its Haar tree's bytes:
/// [`VoxelRef::aiv_map`].
#[derive(Clone, Copy)]
pub struct AivMap<'a> {
    n: u32,
    scaling: f32,
    /// `None` for a constant map (no coefficients kept).
    tree: Option<Tree<'a>>,
}

impl AivMap<'_> {
    /// Asks the processor to start loading the tree's first nodes, so that an [`AivMap::eval`]
    /// issued after other work finds them in cache: a walk meets its voxels' trees scattered
    /// through inflated blocks, and the first load of each missed the cache (half the time
    /// of a look-up in a forest's render).
    #[inline]
    pub fn prefetch(&self) {
        #[cfg(target_arch = "x86_64")]
        if let Some(Tree::F32(t) | Tree::Q16(t)) = self.tree {
            // SAFETY: a prefetch is a hint; it reads nothing and cannot fault.
            unsafe {
                use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
                _mm_prefetch::<_MM_HINT_T0>(t.as_ptr() as *const i8);
                if t.len() > 64 {
                    _mm_prefetch::<_MM_HINT_T0>(t.as_ptr().add(64) as *const i8);
                }
            }
        }
    }

    /// The interior visibility towards `d` (unit), walking one path of the tree.
    #[inline]
    pub fn eval(&self, d: Vec3) -> f32 {
        self.eval_cell(self.cell(d).unwrap_or(0))
    }

    /// The cell of the map holding direction `d` (unit): the map is constant over a cell, so
    /// [`AivMap::eval_cell`] of it is [`AivMap::eval`] of `d`. `None` for a constant map.
    #[inline]
    pub fn cell(&self, d: Vec3) -> Option<u32> {
        self.tree
            .map(|_| grid_cell(equal_area_sphere_to_square(d), self.n))
    }

    /// The map's value in cell `cell` ([`AivMap::cell`]; any cell for a constant map).
    #[inline]
    pub fn eval_cell(&self, cell: u32) -> f32 {
        let n = self.n;
        match self.tree {
            None => (self.scaling / n.max(1) as f32).clamp(0.0, 1.0),
            // A visibility: truncated wavelets may ring slightly outside [0, 1].
            Some(tree) => eval_bytes(n, self.scaling, tree, cell),
        }
    }
}

/// Node `i` of a float tree's raw bytes, decoded (the look-ups' hot path: no accessor calls).
#[inline]
fn node_at(tree: &[u8], i: usize) -> Node {
    let b = &tree[i * NODE_BYTES..(i + 1) * NODE_BYTES];
    let f = |o: usize| f32::from_le_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]]);
    Node {
        details: [f(0), f(4), f(8)],
        subtree: u32::from_le_bytes([b[12], b[13], b[14], b[15]]),
        children: b[16],
    }
}

/// A verified tree's value at cell (x, y), walking one path ([`eval_tree`]); in [0, 1] (a
/// non-finite value, which verification rules out, is counted and replaced).
#[inline]
fn eval_bytes(n: u32, scaling: f32, tree: Tree, cell: u32) -> f32 {
    let (x, y) = (cell % n, cell / n);
    let v = match tree {
        Tree::F32(t) => eval_tree(n, scaling, t.len() / NODE_BYTES, |i, _| node_at(t, i), x, y),
        Tree::Q16(t) => eval_q16(n, scaling, t, x, y),
    };
    crate::math::finite_or_zero(v).clamp(0.0, 1.0)
}

/// [`eval_tree`] on a fixed-point tree's raw bytes, in integers. A node of a block `size`
/// wide stores its details as round(h / size · [`Q_DETAIL`]), and a detail h adds ±h / size
/// to a cell, so the path's sum is ±q / [`Q_DETAIL`] summed over its nodes: one integer sum
/// and one division, where the generic walk decoded each node to floats and divided by its
/// size (the AIV look-ups of a walk's hits were 29% of a forest's render, most of it there).
/// Equal to [`eval_tree`] on [`QNode::node`]'s decoding up to f32 rounding of size / 254.
#[inline]
fn eval_q16(n: u32, scaling: f32, t: &[u8], x: u32, y: u32) -> f32 {
    let n = n.max(1);
    let len = t.len() / QNODE_BYTES;
    let links = |i: usize| u16::from_le_bytes([t[i * QNODE_BYTES], t[i * QNODE_BYTES + 1]]);
    let mut acc = 0i32;
    let mut i = 0usize;
    let mut half = n / 2;
    let (mut x0, mut y0) = (0u32, 0u32);
    while i < len && half > 0 {
        let b = &t[i * QNODE_BYTES..i * QNODE_BYTES + QNODE_BYTES];
        let children = b[1] >> 4;
        let right = x >= x0 + half;
        let bottom = y >= y0 + half;
        let (h, v, d) = (b[2] as i8 as i32, b[3] as i8 as i32, b[4] as i8 as i32);
        let h = if right { -h } else { h };
        let v = if bottom { -v } else { v };
        let d = if right != bottom { -d } else { d };
        acc += h + v + d;
        let q = (right as u8) | ((bottom as u8) << 1);
        if children & (1 << q) == 0 {
            break;
        }
        // Skip the subtrees of earlier present siblings.
        let mut j = i + 1;
        for p in 0..q {
            if children & (1 << p) != 0 && j < len {
                j += (links(j) & 0x0fff) as usize;
            }
        }
        i = j;
        x0 += if right { half } else { 0 };
        y0 += if bottom { half } else { 0 };
        half /= 2;
    }
    (scaling as f64 / n as f64 + acc as f64 / Q_DETAIL as f64) as f32
}

/// Moment set `i` of a verified voxel block: full (`metal`) or dielectric, in either layout.
fn moments_at(b: &fb::Block, metal: bool, i: usize) -> MaterialMoments {
    use super::quantize;
    match (metal, b.qmoments(), b.qdielectric_moments()) {
        (true, Some(q), _) => quantize::moments(q.get(i)),
        (false, _, Some(q)) => quantize::dielectric_moments(q.get(i)),
        (true, ..) => {
            let x = b.moments().expect("verified").get(i);
            MaterialMoments {
                c: g(x.base()),
                mc: g(x.metal_base()),
                s: x.specular(),
                ms: x.metal_specular(),
                m: x.metallic(),
                f90: x.f90(),
                mf90: x.metal_f90(),
            }
        }
        (false, ..) => {
            let x = b.dielectric_moments().expect("verified").get(i);
            MaterialMoments {
                c: g(x.base()),
                s: x.specular(),
                f90: x.f90(),
                ..Default::default()
            }
        }
    }
}

/// A block's SGGX lobes, in either layout.
#[derive(Clone, Copy)]
enum Lobes<'a> {
    F32(flatbuffers::Vector<'a, fb::Lobe>),
    Q16(flatbuffers::Vector<'a, fb::QLobe>),
}

impl<'a> Lobes<'a> {
    fn of(b: &fb::Block<'a>) -> Lobes<'a> {
        match b.qlobes() {
            Some(q) => Lobes::Q16(q),
            None => Lobes::F32(b.lobes().expect("verified")),
        }
    }

    fn len(&self) -> usize {
        match self {
            Lobes::F32(v) => v.len(),
            Lobes::Q16(v) => v.len(),
        }
    }

    fn get(&self, i: usize) -> NdfLobe {
        match self {
            Lobes::F32(v) => {
                let l = v.get(i);
                NdfLobe {
                    weight: l.weight(),
                    frame: Mat3::from_cols(g(l.t()), g(l.b()), g(l.n())),
                    alpha: Vec2::new(l.alpha_x(), l.alpha_y()),
                }
            }
            Lobes::Q16(v) => super::quantize::lobe(v.get(i)),
        }
    }
}

pub(crate) fn verifier_options() -> flatbuffers::VerifierOptions {
    flatbuffers::VerifierOptions {
        max_depth: 16,
        max_tables: 1 << 24,
        max_apparent_size: 1 << 31,
        ignore_missing_null_terminator: false,
    }
}

impl Aggregate {
    /// Maps a file and verifies all of it.
    pub fn open(path: &Path) -> Result<Aggregate, FormatError> {
        let a = Self::mapped(path, true)?;
        a.verify_all()?;
        Ok(a)
    }

    /// Maps a file and verifies its header and index only; each block is verified the first
    /// time it is read. Opening a file of any size takes milliseconds.
    ///
    /// A block read lazily gets every check of [`Aggregate::open`] (checksum, structure,
    /// ranges, finite records) except the walk over each visibility tree's shape, which is a
    /// fifth of the time of preparing a level: the tree look-ups are bounds-checked and depth-
    /// limited on any bytes and clamp their value to [0, 1], so a malformed tree that passed
    /// the checksum gives wrong visibility, never a panic. [`Aggregate::open`] walks them.
    pub fn open_lazy(path: &Path) -> Result<Aggregate, FormatError> {
        Self::mapped(path, false)
    }

    /// [`Aggregate::from_bytes_lazy`] without the CRC-32s, verifying nothing until a block is
    /// read: for the tests that show damage reaching a lazily read block cannot panic.
    #[doc(hidden)]
    pub fn from_bytes_lazy_ignoring_checksums(bytes: Vec<u8>) -> Result<Aggregate, FormatError> {
        Self::indexed(Backing::Owned(bytes), false, false)
    }

    fn mapped(path: &Path, trees: bool) -> Result<Aggregate, FormatError> {
        let file = File::open(path)?;
        let len = file.metadata()?.len();
        if len == 0 {
            return Err(FormatError::Truncated {
                expected: HEADER_SIZE as u64,
                actual: 0,
            });
        }
        // SAFETY: the map is read-only; the usual caveat of memory maps applies (another
        // process truncating the file while it is mapped), as for every mapped-file reader.
        let map = unsafe { memmap2::Mmap::map(&file)? };
        Self::indexed(Backing::Map(map), true, trees)
    }

    /// Verifies an in-memory file, all of it.
    pub fn from_bytes(bytes: Vec<u8>) -> Result<Aggregate, FormatError> {
        let a = Self::indexed(Backing::Owned(bytes), true, true)?;
        a.verify_all()?;
        Ok(a)
    }

    /// An in-memory file with its header and index verified; blocks on first use, as for
    /// [`Aggregate::open_lazy`].
    pub fn from_bytes_lazy(bytes: Vec<u8>) -> Result<Aggregate, FormatError> {
        Self::indexed(Backing::Owned(bytes), true, false)
    }

    /// Verifies an in-memory file with every check but the CRC-32s: for fuzzing, where
    /// random bytes would otherwise never get past the checksums to the structural checks.
    pub fn from_bytes_ignoring_checksums(bytes: Vec<u8>) -> Result<Aggregate, FormatError> {
        let a = Self::indexed(Backing::Owned(bytes), false, true)?;
        a.verify_all()?;
        Ok(a)
    }

    /// `trees`: whether block verification walks each visibility tree's shape.
    fn indexed(data: Backing, checksums: bool, trees: bool) -> Result<Aggregate, FormatError> {
        let bytes: &[u8] = match &data {
            Backing::Map(m) => m,
            Backing::Owned(v) => v,
        };
        let header = Header::parse_with(bytes, checksums)?;
        let (settings, levels, blobs) = verify_index(bytes, &header, checksums)?;
        Ok(Aggregate {
            data,
            header,
            checksums,
            trees,
            settings,
            levels,
            blobs,
        })
    }

    /// Verifies every block not verified yet (in parallel); the first failure is returned.
    pub fn verify_all(&self) -> Result<(), FormatError> {
        use rayon::prelude::*;
        (0..self.blobs.len())
            .into_par_iter()
            .try_for_each(|i| self.check(i).map(|_| ()))
    }

    /// The file's bytes.
    pub fn bytes(&self) -> &[u8] {
        match &self.data {
            Backing::Map(m) => m,
            Backing::Owned(v) => v,
        }
    }

    /// The fixed header.
    pub fn header(&self) -> Header {
        self.header
    }

    /// The index (verified on open).
    pub(crate) fn index(&self) -> fb::Index<'_> {
        let h = &self.header;
        let b = &self.bytes()[h.index_offset as usize..(h.index_offset + h.index_size) as usize];
        // SAFETY: verified by `verify_index` on open, and the bytes are immutable since.
        unsafe { flatbuffers::root_unchecked::<fb::Index>(b) }
    }

    /// The bake settings the file records.
    pub fn settings(&self) -> &RecordedSettings {
        &self.settings
    }

    /// The generator, e.g. "aggtool 0.1.0".
    pub fn generator(&self) -> &str {
        self.index().generator().unwrap_or("")
    }

    /// The source asset's file name.
    pub fn source(&self) -> &str {
        self.index().source().unwrap_or("")
    }

    /// The source asset's bounds.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        let ix = self.index();
        (
            ix.bounds_min().map_or(Vec3::ZERO, g),
            ix.bounds_max().map_or(Vec3::ZERO, g),
        )
    }

    /// Version and CRC-32 of the M1–M5 tables the file was baked with.
    pub fn tables(&self) -> (u32, u32) {
        let ix = self.index();
        (ix.tables_version(), ix.tables_crc32())
    }

    /// The number of levels (finest first).
    pub fn level_count(&self) -> usize {
        self.levels.len()
    }

    /// The grid of level `l`.
    pub fn grid(&self, l: usize) -> Grid {
        self.levels[l].grid
    }

    /// The level whose voxels hold level `l`'s interior visibility: `l` itself, or for a
    /// visibility level (finer than the recorded `shading_res`, format 1.7) the level of that
    /// resolution, whose voxel containing a voxel of `l` gives its AIV and exposure.
    pub fn shading_level(&self, l: usize) -> usize {
        let r = self.settings.shading_res;
        if r == 0 || self.levels[l].grid.res <= r {
            return l;
        }
        self.levels
            .iter()
            .position(|x| x.grid.res == r)
            .unwrap_or(l)
    }

    /// The shading level of level `l` ([`Self::shading_level`]) and how many times finer
    /// level `l` is (as a power of two): a voxel v of level `l` is shaded by voxel v >> shift.
    pub fn shading_of(&self, l: usize) -> (usize, u32) {
        let s = self.shading_level(l);
        let (rl, rs) = (self.levels[l].grid.res, self.levels[s].grid.res);
        if s == l || rs >= rl {
            return (l, 0);
        }
        (s, rl.trailing_zeros() - rs.trailing_zeros())
    }

    /// What level `l` stores (counted by the bake).
    pub fn counts(&self, l: usize) -> Counts {
        self.levels[l].counts
    }

    /// Bytes of level `l`'s voxel blocks and face blocks.
    pub fn level_bytes(&self, l: usize) -> (u64, u64) {
        let lv = &self.levels[l];
        let sum = |r: &Range<usize>| self.blobs[r.clone()].iter().map(|b| b.size).sum();
        (sum(&lv.voxel_blobs), sum(&lv.face_blobs))
    }

    /// Bytes of level `l` per component (the arrays' payloads, in whichever layout each block
    /// stores), over its blocks that verify; and whether every tree, lobe and moment array is
    /// in format 1.4's quantized layout.
    pub fn component_bytes(&self, l: usize) -> (ComponentBytes, bool) {
        let lv = &self.levels[l];
        let mut c = ComponentBytes::default();
        let mut quantized = true;
        let n = |b: Option<&[u8]>| b.map_or(0, |b| b.len() as u64);
        for i in lv.voxel_blobs.clone() {
            let Ok(b) = self.check(i) else { continue };
            c.keys += n(b.keys().map(|v| v.bytes()));
            c.voxels += n(b.voxels().map(|v| v.bytes()));
            c.lobes += n(b.lobes().map(|v| v.bytes())) + n(b.qlobes().map(|v| v.bytes()));
            c.moments += n(b.moments().map(|v| v.bytes())) + n(b.qmoments().map(|v| v.bytes()));
            c.dielectric_moments += n(b.dielectric_moments().map(|v| v.bytes()))
                + n(b.qdielectric_moments().map(|v| v.bytes()));
            c.aiv_nodes +=
                n(b.aiv_nodes().map(|v| v.bytes())) + n(b.aiv_qnodes().map(|v| v.bytes()));
            c.exposure += n(b.exposure().map(|v| v.bytes()));
            quantized &= b.qlobes().is_some() && b.aiv_qnodes().is_some();
        }
        for i in lv.face_blobs.clone() {
            let Ok(b) = self.check(i) else { continue };
            c.faces += n(b.faces().map(|v| v.bytes()));
            c.abv_nodes +=
                n(b.abv_nodes().map(|v| v.bytes())) + n(b.abv_qnodes().map(|v| v.bytes()));
            quantized &= b.abv_qnodes().is_some();
        }
        (c, quantized)
    }

    /// Voxel and face blocks of level `l`.
    pub fn block_counts(&self, l: usize) -> (usize, usize) {
        let lv = &self.levels[l];
        (lv.voxel_blobs.len(), lv.face_blobs.len())
    }

    /// Verifies blob `i` if it was not yet, and returns its block.
    fn check(&self, i: usize) -> Result<fb::Block<'_>, FormatError> {
        let b = &self.blobs[i];
        let state = b.checked.get_or_init(|| self.check_blob(b));
        match state {
            Ok(inflated) => Ok(self.block_unchecked(b, inflated.as_deref())),
            Err(e) => Err(FormatError::Corrupt(e.clone())),
        }
    }

    /// The block of a verified blob: in the file, or inflated (`inflated`, a compressed blob).
    fn block_unchecked<'s>(&'s self, b: &Blob, inflated: Option<&'s [u8]>) -> fb::Block<'s> {
        let bytes =
            inflated.unwrap_or(&self.bytes()[b.offset as usize..(b.offset + b.size) as usize]);
        // SAFETY: only called for a blob that passed `check_blob` (the FlatBuffers verifier and
        // the invariants), and the bytes are immutable.
        unsafe { flatbuffers::root_unchecked::<fb::Block>(bytes) }
    }

    /// Bytes of level `l`'s blocks as stored and as read (inflated; the same for blocks
    /// stored uncompressed), over its blocks that verify.
    pub fn stored_and_inflated_bytes(&self, l: usize) -> (u64, u64) {
        let lv = &self.levels[l];
        let (mut stored, mut inflated) = (0, 0);
        for i in lv.voxel_blobs.clone().chain(lv.face_blobs.clone()) {
            if self.check(i).is_err() {
                continue;
            }
            let b = &self.blobs[i];
            stored += b.size;
            inflated += match b.checked.get() {
                Some(Ok(Some(z))) => z.len() as u64,
                _ => b.size,
            };
        }
        (stored, inflated)
    }

    /// Voxel block `i` of level `l`, verified.
    pub fn voxel_block(&self, l: usize, i: usize) -> Result<VoxelBlock<'_>, FormatError> {
        let lv = &self.levels[l];
        let bi = lv.voxel_blobs.start + i;
        if bi >= lv.voxel_blobs.end {
            return Err(corrupt(format!("level {l} has no voxel block {i}")));
        }
        let block = self.check(bi)?;
        Ok(VoxelBlock {
            block,
            keys: block.keys().expect("verified"),
            recs: block.voxels().expect("verified"),
            aiv_res: self.settings.aiv_res,
        })
    }

    /// Face block `i` of level `l`, verified.
    pub fn face_block(&self, l: usize, i: usize) -> Result<FaceBlock<'_>, FormatError> {
        let lv = &self.levels[l];
        let bi = lv.face_blobs.start + i;
        if bi >= lv.face_blobs.end {
            return Err(corrupt(format!("level {l} has no face block {i}")));
        }
        let block = self.check(bi)?;
        Ok(FaceBlock {
            faces: block.faces().expect("verified"),
            nodes: Nodes::abv(&block),
            abv_res: self.settings.abv_res,
        })
    }

    /// Voxel block `i` of level `l`, verified, with bytes the caller owns: for a cache that
    /// frees what it evicts ([`crate::runtime::BlockCache`]). A block stored uncompressed is
    /// read in place from the file; a compressed one (format 1.5) is inflated afresh each
    /// call and kept by nobody but the caller. Verification runs on the first call only (its
    /// verdict is kept, a few bytes); a block [`Aggregate::open`] already verified and
    /// inflated is lent from there.
    pub fn load_voxel_block(&self, l: usize, i: usize) -> Result<LoadedBlock<'_>, FormatError> {
        let lv = &self.levels[l];
        let bi = lv.voxel_blobs.start + i;
        if bi >= lv.voxel_blobs.end {
            return Err(corrupt(format!("level {l} has no voxel block {i}")));
        }
        self.load_block(bi)
    }

    /// Face block `i` of level `l` as [`Aggregate::load_voxel_block`] loads voxel blocks.
    pub fn load_face_block(&self, l: usize, i: usize) -> Result<LoadedBlock<'_>, FormatError> {
        let lv = &self.levels[l];
        let bi = lv.face_blobs.start + i;
        if bi >= lv.face_blobs.end {
            return Err(corrupt(format!("level {l} has no face block {i}")));
        }
        self.load_block(bi)
    }

    /// The first and last voxel keys of level `l`'s voxel blocks and their voxel counts, as
    /// the index gives them (nothing is read from the blocks).
    pub fn voxel_block_ranges(&self, l: usize) -> Vec<(u64, u64, u32)> {
        self.blobs[self.levels[l].voxel_blobs.clone()]
            .iter()
            .map(|b| (b.first_key, b.last_key, b.count))
            .collect()
    }

    /// The first and last voxel keys of level `l`'s face blocks and their face counts.
    pub fn face_block_ranges(&self, l: usize) -> Vec<(u64, u64, u32)> {
        self.blobs[self.levels[l].face_blobs.clone()]
            .iter()
            .map(|b| (b.first_key, b.last_key, b.count))
            .collect()
    }

    /// Level `l`'s voxel keys from the index (`Level.voxel_keys`, written since 2026-12-06),
    /// checked against its voxel blocks' counts and first and last keys; `None` where the file
    /// has none, so that the caller reads the keys from the blocks.
    pub fn voxel_keys(&self, l: usize) -> Option<Result<Vec<u64>, FormatError>> {
        let lv = self.index().levels()?.get(l);
        let bytes = lv.voxel_keys()?.bytes();
        let blobs = &self.blobs[self.levels[l].voxel_blobs.clone()];
        let count: u64 = blobs.iter().map(|b| b.count as u64).sum();
        let limit = (self.levels[l].grid.res as u64).pow(3);
        let check = || -> Result<Vec<u64>, String> {
            let keys = super::decode_voxel_keys(bytes, count, limit)?;
            let mut at = 0usize;
            for b in blobs {
                let n = b.count as usize;
                let run = keys.get(at..at + n).filter(|r| !r.is_empty());
                if run.is_none_or(|r| r[0] != b.first_key || r[n - 1] != b.last_key) {
                    return Err(format!(
                        "voxel keys disagree with the block at {}",
                        b.offset
                    ));
                }
                at += n;
            }
            Ok(keys)
        };
        Some(check().map_err(|e| corrupt(format!("level {l}: {e}"))))
    }

    /// Verifies blob `b` with this file's settings ([`check_blob`]).
    fn check_blob(&self, b: &Blob) -> Result<Option<Box<[u8]>>, String> {
        check_blob(
            self.bytes(),
            b,
            &self.settings,
            self.levels.as_slice(),
            self.checksums,
            self.trees,
            self.header.minor,
        )
    }

    /// Blob `bi`, verified once, its bytes lent from the file or from `open`'s kept copy, or
    /// inflated for the caller.
    fn load_block(&self, bi: usize) -> Result<LoadedBlock<'_>, FormatError> {
        let b = &self.blobs[bi];
        let (aiv_res, abv_res) = (self.settings.aiv_res, self.settings.abv_res);
        let loaded = |bytes| LoadedBlock {
            bytes,
            voxels: matches!(b.kind, BlobKind::Voxels(_)),
            aiv_res,
            abv_res,
        };
        match b.checked.get() {
            Some(Ok(Some(kept))) => return Ok(loaded(LoadedBytes::InFile(kept))),
            Some(Ok(None)) => return Ok(loaded(LoadedBytes::InFile(self.stored(b)))),
            Some(Err(e)) => return Err(corrupt(e.clone())),
            None => {}
        }
        let mut fresh = None;
        let verdict = b
            .verdict
            .get_or_init(|| self.check_blob(b).map(|inflated| fresh = inflated));
        if let Err(e) = verdict {
            return Err(corrupt(e.clone()));
        }
        let stored = self.stored(b);
        let bytes = match fresh {
            Some(inflated) => LoadedBytes::Inflated(inflated),
            None if super::is_coded(stored) => LoadedBytes::Inflated(
                super::inflate_block(stored)
                    .map_err(|e| corrupt(format!("block at {}: {e}", b.offset)))?
                    .into_boxed_slice(),
            ),
            None => return Ok(loaded(LoadedBytes::InFile(stored))),
        };
        self.release(b);
        Ok(loaded(bytes))
    }

    /// Drops the mapped pages of a compressed blob that has been inflated, so that the
    /// process's resident memory is the cache's and not the file's: a cache that evicts the
    /// block and loads it again reads the pages back from the page cache. Without this, every
    /// block a render ever touched stays resident as mapped file pages (233 MiB of a 354 MiB
    /// peak for the 1M-triangle foliage's 256³ near view under a 64 MiB budget).
    #[cfg_attr(not(unix), allow(unused_variables))]
    fn release(&self, b: &Blob) {
        #[cfg(unix)]
        if let Backing::Map(m) = &self.data {
            const PAGE: usize = 4096;
            let (start, end) = (b.offset as usize, (b.offset + b.size) as usize);
            // Whole pages inside the blob only: a page shared with a neighbour that a cone
            // is reading stays.
            let (first, last) = (start.div_ceil(PAGE) * PAGE, end / PAGE * PAGE);
            if last > first {
                // SAFETY: the mapping is read-only and never written, so dropping its pages
                // changes no byte any slice of it sees (another thread reading this blob
                // faults the same file bytes back in); the blob was inflated into an owned
                // buffer. On a machine with larger pages the call fails and changes nothing.
                let _ = unsafe {
                    m.unchecked_advise_range(
                        memmap2::UncheckedAdvice::DontNeed,
                        first,
                        last - first,
                    )
                };
            }
        }
    }

    fn stored(&self, b: &Blob) -> &[u8] {
        &self.bytes()[b.offset as usize..(b.offset + b.size) as usize]
    }

    /// The voxel with Morton key `key` at level `l`, found by binary search over the blocks'
    /// key ranges and then over the block's keys. `None` also when its block fails to verify.
    pub fn find_voxel(&self, l: usize, key: u64) -> Option<VoxelRef<'_>> {
        let lv = self.levels.get(l)?;
        let blobs = &self.blobs[lv.voxel_blobs.clone()];
        let i = blobs.partition_point(|b| b.last_key < key);
        if i >= blobs.len() || blobs[i].first_key > key {
            return None;
        }
        let block = self.voxel_block(l, i).ok()?;
        let keys = block.keys;
        let (mut a, mut b) = (0usize, keys.len());
        while a < b {
            let m = (a + b) / 2;
            if keys.get(m) < key {
                a = m + 1;
            } else {
                b = m;
            }
        }
        (a < keys.len() && keys.get(a) == key).then(|| block.voxel(a))
    }

    /// Every voxel of level `l` in Morton order (of the blocks that verify: every one for a
    /// file opened with [`Aggregate::open`]).
    pub fn voxels(&self, l: usize) -> impl Iterator<Item = VoxelRef<'_>> + '_ {
        let n = self.levels[l].voxel_blobs.len();
        (0..n)
            .filter_map(move |i| self.voxel_block(l, i).ok())
            .flat_map(|b| (0..b.len()).map(move |i| b.voxel(i)))
    }

    /// Every boundary face of level `l` (of the blocks that verify).
    pub fn faces(&self, l: usize) -> impl Iterator<Item = FaceRef<'_>> + '_ {
        let n = self.levels[l].face_blobs.len();
        (0..n)
            .filter_map(move |i| self.face_block(l, i).ok())
            .flat_map(|b| (0..b.len()).map(move |i| b.face(i)))
    }

    /// Decodes level `l` into memory (tests, tools; renderers read zero-copy instead).
    pub fn read_level(&self, l: usize) -> LevelData {
        let voxels = self
            .voxels(l)
            .map(|v| VoxelData {
                key: v.key,
                area: v.area() as f64,
                coverage: v.coverage(),
                appearance: v.appearance(),
                ellipsoid: v.ellipsoid(),
                aiv: v.aiv_tree(),
                exposure: v.exposure(),
            })
            .collect();
        let faces = self
            .faces(l)
            .map(|f| FaceData {
                face: f.face(),
                abv: f.abv_tree(),
            })
            .collect();
        LevelData {
            grid: self.grid(l),
            voxels,
            faces,
            rays: 0,
        }
    }
}

/// The bytes of a verified block: in the file, or inflated and owned.
enum LoadedBytes<'a> {
    InFile(&'a [u8]),
    Inflated(Box<[u8]>),
}

/// A verified block whose bytes its holder owns ([`Aggregate::load_voxel_block`],
/// [`Aggregate::load_face_block`]): read with [`LoadedBlock::voxels`] or
/// [`LoadedBlock::faces`], zero-copy.
pub struct LoadedBlock<'a> {
    bytes: LoadedBytes<'a>,
    voxels: bool,
    aiv_res: u32,
    abv_res: u32,
}

impl LoadedBlock<'_> {
    fn block(&self) -> fb::Block<'_> {
        let bytes: &[u8] = match &self.bytes {
            LoadedBytes::InFile(b) => b,
            LoadedBytes::Inflated(b) => b,
        };
        // SAFETY: a `LoadedBlock` is only made of bytes that passed `check_blob` (the
        // FlatBuffers verifier and the invariants the accessors rely on), and they are
        // immutable.
        unsafe { flatbuffers::root_unchecked::<fb::Block>(bytes) }
    }

    /// The bytes held in memory for the block (0 for a block read in place from the file or
    /// lent by the aggregate).
    pub fn owned_bytes(&self) -> usize {
        match &self.bytes {
            LoadedBytes::InFile(_) => 0,
            LoadedBytes::Inflated(b) => b.len(),
        }
    }

    /// The block's voxels; `None` for a face block.
    pub fn voxels(&self) -> Option<VoxelBlock<'_>> {
        if !self.voxels {
            return None;
        }
        let block = self.block();
        Some(VoxelBlock {
            block,
            keys: block.keys()?,
            recs: block.voxels()?,
            aiv_res: self.aiv_res,
        })
    }

    /// The block's faces; `None` for a voxel block.
    pub fn faces(&self) -> Option<FaceBlock<'_>> {
        if self.voxels {
            return None;
        }
        let block = self.block();
        Some(FaceBlock {
            faces: block.faces()?,
            nodes: Nodes::abv(&block),
            abv_res: self.abv_res,
        })
    }
}

/// A verified block of voxels, read zero-copy.
#[derive(Clone, Copy)]
pub struct VoxelBlock<'a> {
    block: fb::Block<'a>,
    keys: flatbuffers::Vector<'a, u64>,
    recs: flatbuffers::Vector<'a, fb::Voxel>,
    aiv_res: u32,
}

impl<'a> VoxelBlock<'a> {
    /// Voxels in the block.
    pub fn len(&self) -> usize {
        self.keys.len()
    }

    /// Whether the block holds no voxel (never, for a verified block).
    pub fn is_empty(&self) -> bool {
        self.keys.is_empty()
    }

    /// The Morton key of voxel `i`.
    pub fn key(&self, i: usize) -> u64 {
        self.keys.get(i)
    }

    /// Voxel `i` (in ascending key order).
    pub fn voxel(&self, i: usize) -> VoxelRef<'a> {
        VoxelRef {
            key: self.keys.get(i),
            rec: self.recs.get(i),
            block: self.block,
            index: i as u32,
            aiv_res: self.aiv_res,
        }
    }
}

/// A verified block of boundary faces, read zero-copy.
#[derive(Clone, Copy)]
pub struct FaceBlock<'a> {
    faces: flatbuffers::Vector<'a, fb::Face>,
    nodes: Nodes<'a>,
    abv_res: u32,
}

impl<'a> FaceBlock<'a> {
    /// Faces in the block.
    pub fn len(&self) -> usize {
        self.faces.len()
    }

    /// Whether the block holds no face.
    pub fn is_empty(&self) -> bool {
        self.faces.is_empty()
    }

    /// Face `i`.
    pub fn face(&self, i: usize) -> FaceRef<'a> {
        FaceRef {
            rec: self.faces.get(i),
            nodes: self.nodes,
            abv_res: self.abv_res,
        }
    }

    /// The ABV of a face of this block ([`FaceRef::abv_ref`]) towards `d`, as
    /// [`FaceRef::abv`].
    #[inline]
    pub fn abv(&self, face: &FaceAbv, d: Vec3) -> f32 {
        face.eval(self.nodes, self.abv_res, d)
    }
}

/// What the ABV look-up reads of a face (16 bytes): its direction and where its tree's
/// nodes are in the block, for a runtime that keeps its faces sorted by key without the
/// pointer into the block that a [`FaceRef`] is (one dependent load fewer a look-up, 16 bytes
/// a face instead of 40).
#[derive(Clone, Copy, Debug)]
pub struct FaceAbv {
    start: u32,
    count: u32,
    scaling: f32,
    dir: u8,
}

impl FaceAbv {
    /// The ABV towards unit `d` (Eq. 26), read from the tree's nodes in `nodes`.
    #[inline]
    fn eval(&self, nodes: Nodes<'_>, n: u32, d: Vec3) -> f32 {
        if self.count == 0 {
            return (self.scaling / n.max(1) as f32).clamp(0.0, 1.0);
        }
        let local = Frame::from_z(-face_normal(self.dir)).to_local(d);
        if !(local.z > 0.0) {
            return (self.scaling / n as f32).clamp(0.0, 1.0);
        }
        let cell = grid_cell(concentric_hemisphere_to_square(local), n);
        let tree = nodes.tree(self.start as usize, self.count as usize);
        eval_bytes(n, self.scaling, tree, cell)
    }
}

/// A boundary face and its ABV tree, read zero-copy.
#[derive(Clone, Copy)]
pub struct FaceRef<'a> {
    rec: &'a fb::Face,
    nodes: Nodes<'a>,
    abv_res: u32,
}

impl<'a> FaceRef<'a> {
    /// The face: its voxel and direction.
    pub fn face(&self) -> Face {
        Face {
            voxel: UVec3Key(self.rec.x(), self.rec.y(), self.rec.z()),
            dir: self.rec.dir() as u8,
        }
    }

    /// The Morton key of the face's voxel.
    pub fn key(&self) -> u64 {
        morton3(UVec3::new(self.rec.x(), self.rec.y(), self.rec.z()))
    }

    /// The mean of the ABV map.
    pub fn mean(&self) -> f32 {
        self.rec.abv_scaling() / self.abv_res.max(1) as f32
    }

    /// The boundary visibility (Eq. 26) towards unit `d`, which points into the aggregate
    /// through the face, walking one path of the tree; the map's mean for directions that do
    /// not enter through the face.
    #[inline]
    pub fn abv(&self, d: Vec3) -> f32 {
        self.abv_ref().eval(self.nodes, self.abv_res, d)
    }

    /// What the ABV look-up reads of this face, without the pointer into the block.
    pub fn abv_ref(&self) -> FaceAbv {
        FaceAbv {
            start: self.rec.abv_start(),
            count: self.rec.abv_count(),
            scaling: self.rec.abv_scaling(),
            dir: self.rec.dir() as u8,
        }
    }

    /// The decoded ABV tree.
    pub fn abv_tree(&self) -> SparseHaar {
        self.nodes.decode(
            self.abv_res,
            self.rec.abv_scaling(),
            self.rec.abv_start() as usize,
            self.rec.abv_count() as usize,
        )
    }
}

/// A voxel record inside its block, read zero-copy.
#[derive(Clone, Copy)]
pub struct VoxelRef<'a> {
    /// The voxel's Morton key.
    pub key: u64,
    rec: &'a fb::Voxel,
    block: fb::Block<'a>,
    /// Position in the block.
    index: u32,
    aiv_res: u32,
}

impl<'a> VoxelRef<'a> {
    /// The exposure η in [1/16, 1] (format 1.1; 1 where the block stores none).
    pub fn exposure(&self) -> f32 {
        self.block
            .exposure()
            .map_or(1.0, |e| e.get(self.index as usize))
    }

    /// The voxel's coordinates in its level.
    pub fn coords(&self) -> UVec3 {
        demorton3(self.key)
    }

    /// Surface area inside the voxel, before cut-outs.
    pub fn area(&self) -> f32 {
        self.rec.area()
    }

    /// The fraction of the area left after cut-outs.
    pub fn coverage(&self) -> f32 {
        self.rec.coverage()
    }

    /// The voxel's ellipsoid.
    pub fn ellipsoid(&self) -> Ellipsoid {
        let r = self.rec;
        Ellipsoid {
            center: g(r.center()),
            axes: Mat3::from_cols(g(r.axis_x()), g(r.axis_y()), g(r.axis_z())),
        }
    }

    /// The mean of the AIV map.
    pub fn aiv_mean(&self) -> f32 {
        self.rec.aiv_scaling() / self.aiv_res.max(1) as f32
    }

    /// The interior visibility towards `d` (unit), walking one path of the tree.
    #[inline]
    pub fn aiv(&self, d: Vec3) -> f32 {
        self.aiv_map().eval(d)
    }

    /// The voxel's AIV map with its fields read out of the record once: for a holder that
    /// looks it up many times ([`AivMap::eval`] is [`VoxelRef::aiv`] without the
    /// FlatBuffers accessors, 7% of a LoD render).
    #[inline]
    pub fn aiv_map(&self) -> AivMap<'a> {
        let r = self.rec;
        let (start, count) = (r.aiv_start() as usize, r.aiv_count() as usize);
        AivMap {
            n: self.aiv_res,
            scaling: r.aiv_scaling(),
            tree: (count > 0).then(|| Nodes::aiv(&self.block).tree(start, count)),
        }
    }

    /// The decoded AIV tree.
    pub fn aiv_tree(&self) -> SparseHaar {
        let r = self.rec;
        Nodes::aiv(&self.block).decode(
            self.aiv_res,
            r.aiv_scaling(),
            r.aiv_start() as usize,
            r.aiv_count() as usize,
        )
    }

    /// The voxel's SGGX lobes (Eq. 8), without allocating.
    pub fn lobes(&self) -> impl Iterator<Item = NdfLobe> + 'a {
        let r = self.rec;
        let lobes = Lobes::of(&self.block);
        (r.lobe_start()..r.lobe_start() + r.lobe_count()).map(move |i| lobes.get(i as usize))
    }

    /// The voxel's directional moments in place, where its block stores them quantized (format
    /// 1.4): the binary16 sets [`VoxelRef::absdf`] reads without a copy.
    /// `None` for constant moments, f32 moments, or bytes a `u16` slice cannot view (a
    /// big-endian machine; an unaligned vector).
    pub fn moment_halves(&self) -> Option<MomentHalves<'a>> {
        let r = self.rec;
        if !r.flags().contains(fb::VoxelFlags::DirectionalMoments) || cfg!(target_endian = "big") {
            return None;
        }
        let metal = r.flags().contains(fb::VoxelFlags::Metallic);
        let (bytes, size) = if metal {
            (
                self.block.qmoments()?.bytes(),
                std::mem::size_of::<fb::QMoments>(),
            )
        } else {
            (
                self.block.qdielectric_moments()?.bytes(),
                std::mem::size_of::<fb::QDielectricMoments>(),
            )
        };
        let (start, count) = (r.moment_start() as usize, r.moment_count() as usize);
        let bytes = bytes.get(start * size..(start + count) * size)?;
        // SAFETY: any two bytes are a valid u16; `align_to` puts only aligned ones in the middle.
        let (pre, halves, post) = unsafe { bytes.align_to::<u16>() };
        (pre.is_empty() && post.is_empty()).then_some(MomentHalves {
            res: r.moment_res(),
            metal,
            halves,
        })
    }

    /// The voxel's ABSDF as the runtime builds it: the directional moments read in place
    /// where the block stores them quantized ([`VoxelRef::moment_halves`]), else decoded (the
    /// same function as `Absdf::new(&self.appearance(), tables)`, bit for bit).
    pub fn absdf<'t>(&self, tables: &'t crate::tables::Tables) -> crate::absdf::Absdf<'t>
    where
        'a: 't,
    {
        let r = self.rec;
        self.moment_halves()
            .and_then(|h| {
                let lobes: Vec<NdfLobe> = self.lobes().collect();
                crate::absdf::Absdf::with_moment_halves(
                    &lobes,
                    r.roughness_mean(),
                    r.roughness_variance(),
                    h,
                    tables,
                )
            })
            .unwrap_or_else(|| crate::absdf::Absdf::new(&self.appearance(), tables))
    }

    /// The ABSDF inputs.
    pub fn appearance(&self) -> VoxelAppearance {
        let r = self.rec;
        let lobes = self.lobes().collect();
        let range = r.moment_start() as usize..(r.moment_start() + r.moment_count()) as usize;
        let metal = r.flags().contains(fb::VoxelFlags::Metallic);
        let sets: Vec<MaterialMoments> = range.map(|i| moments_at(&self.block, metal, i)).collect();
        let moments = if r.flags().contains(fb::VoxelFlags::DirectionalMoments) {
            let cells = (r.moment_res() * r.moment_res()) as usize;
            Moments::Directional {
                res: r.moment_res(),
                diffuse: sets[..cells].to_vec(),
                specular: sets[cells..].to_vec(),
            }
        } else {
            Moments::Constant(sets[0])
        };
        VoxelAppearance {
            lobes,
            roughness_mean: r.roughness_mean(),
            roughness_variance: r.roughness_variance(),
            moments,
        }
    }
}

/// Verifies the index: its checksum and structure, the settings, the level table, and that the
/// blobs it names lie in the file, aligned, without overlapping; returns what the reader keeps.
#[allow(clippy::type_complexity)]
fn verify_index(
    data: &[u8],
    h: &Header,
    checksums: bool,
) -> Result<(RecordedSettings, Vec<LevelInfo>, Vec<Blob>), FormatError> {
    let index_bytes = &data[h.index_offset as usize..(h.index_offset + h.index_size) as usize];
    if h.index_offset % ALIGN != 0 {
        return Err(corrupt("index not aligned"));
    }
    if checksums && crc32fast::hash(index_bytes) != h.index_crc32 {
        return Err(corrupt("index checksum mismatch"));
    }
    if !has_identifier(index_bytes, INDEX_ID) {
        return Err(corrupt("index has the wrong identifier"));
    }
    let opts = verifier_options();
    let index = flatbuffers::root_with_opts::<fb::Index>(&opts, index_bytes)
        .map_err(|e| corrupt(format!("index: {e}")))?;
    let settings = index
        .settings()
        .ok_or_else(|| corrupt("no bake settings"))?;
    let settings = RecordedSettings::from_fb(&settings);
    for (what, n) in [("aiv_res", settings.aiv_res), ("abv_res", settings.abv_res)] {
        if !n.is_power_of_two() || n > 1024 {
            return Err(corrupt(format!(
                "{what} {n} is not a power of two up to 1024"
            )));
        }
    }
    let levels = index.levels().ok_or_else(|| corrupt("no level table"))?;
    let mut blobs: Vec<Blob> = Vec::new();
    let mut infos = Vec::with_capacity(levels.len());
    let blob = |r: &fb::BlobRef, kind: BlobKind| -> Result<Blob, FormatError> {
        let end = r.offset().checked_add(r.size());
        if r.offset() < HEADER_SIZE as u64
            || r.offset() % ALIGN != 0
            || end.is_none_or(|e| e > h.index_offset)
        {
            return Err(corrupt(format!(
                "blob at {}+{} out of range",
                r.offset(),
                r.size()
            )));
        }
        Ok(Blob {
            offset: r.offset(),
            size: r.size(),
            first_key: r.first_key(),
            last_key: r.last_key(),
            count: r.count(),
            crc32: r.crc32(),
            kind,
            gap_end: 0,
            checked: OnceLock::new(),
            verdict: OnceLock::new(),
        })
    };
    for (li, lv) in levels.iter().enumerate() {
        let res = lv.res();
        if !res.is_power_of_two() || res > 1 << 20 {
            return Err(corrupt(format!("level {li}: resolution {res}")));
        }
        let origin = lv
            .origin()
            .ok_or_else(|| corrupt(format!("level {li}: no origin")))?;
        if !finite3(origin) || !(lv.size() > 0.0 && lv.size().is_finite()) {
            return Err(corrupt(format!("level {li}: bad extent")));
        }
        let v0 = blobs.len();
        let mut prev_last: Option<u64> = None;
        let mut voxels = 0u64;
        for r in lv.voxel_blocks().into_iter().flatten() {
            if prev_last.is_some_and(|p| p >= r.first_key()) || r.first_key() > r.last_key() {
                return Err(corrupt(format!("level {li}: voxel blocks out of order")));
            }
            prev_last = Some(r.last_key());
            voxels += r.count() as u64;
            blobs.push(blob(r, BlobKind::Voxels(li as u32))?);
        }
        let f0 = blobs.len();
        let mut faces = 0u64;
        for r in lv.face_blocks().into_iter().flatten() {
            faces += r.count() as u64;
            blobs.push(blob(r, BlobKind::Faces(li as u32))?);
        }
        let counts = lv.counts().map(|c| Counts::from_fb(&c)).unwrap_or_default();
        if lv.counts().is_some() && (counts.voxels != voxels || counts.faces != faces) {
            return Err(corrupt(format!(
                "level {li}: counts disagree with its blocks"
            )));
        }
        infos.push(LevelInfo {
            grid: Grid {
                origin: g(origin),
                size: lv.size(),
                res,
            },
            counts,
            voxel_blobs: v0..f0,
            face_blobs: f0..blobs.len(),
        });
    }
    // A visibility level reads the AIV of the level of `shading_res`, which must be there and
    // have the same cube (its voxels contain theirs).
    if settings.shading_res != 0 {
        let r = settings.shading_res;
        let Some(shading) = infos.iter().find(|i| i.grid.res == r) else {
            return Err(corrupt(format!(
                "shading_res {r} names no level of the file"
            )));
        };
        if infos.iter().any(|i| {
            i.grid.res > r
                && (i.grid.origin != shading.grid.origin || i.grid.size != shading.grid.size)
        }) {
            return Err(corrupt(format!(
                "a level finer than shading_res {r} has another cube than the level it is shaded by"
            )));
        }
    }
    for r in index.pca_blocks().into_iter().flatten() {
        blobs.push(blob(r, BlobKind::Reserved)?);
    }
    // Blobs must not overlap; the gaps between them (alignment padding) must be zeros, so that
    // no byte of the file goes unchecked: the gap before the first blob here, each blob's
    // following gap when the blob is verified.
    let mut order: Vec<usize> = (0..blobs.len()).collect();
    order.sort_unstable_by_key(|&i| blobs[i].offset);
    let mut end = HEADER_SIZE as u64;
    for (k, &i) in order.iter().enumerate() {
        let b = &blobs[i];
        if b.offset < end {
            return Err(corrupt("blobs overlap"));
        }
        if k == 0
            && data[end as usize..b.offset as usize]
                .iter()
                .any(|&x| x != 0)
        {
            return Err(corrupt(format!("non-zero padding at {end}")));
        }
        end = b.offset + b.size;
    }
    if end > h.index_offset {
        return Err(corrupt("blobs overlap"));
    }
    if order.is_empty()
        && data[HEADER_SIZE..h.index_offset as usize]
            .iter()
            .any(|&x| x != 0)
    {
        return Err(corrupt(format!("non-zero padding at {HEADER_SIZE}")));
    }
    for k in 0..order.len() {
        let next = order
            .get(k + 1)
            .map_or(h.index_offset, |&j| blobs[j].offset);
        blobs[order[k]].gap_end = next;
    }
    // Reserved blobs are not read by this version: their bytes are verified now.
    for &i in &order {
        if blobs[i].kind == BlobKind::Reserved {
            let b = &blobs[i];
            let bytes = &data[b.offset as usize..(b.offset + b.size) as usize];
            if checksums && crc32fast::hash(bytes) != b.crc32 {
                return Err(corrupt(format!("blob at {}: checksum mismatch", b.offset)));
            }
            check_gap(data, b)?;
            let _ = b.checked.set(Ok(None));
        }
    }
    Ok((settings, infos, blobs))
}

/// The voxel keys of a voxel block as stored (compressed or not), verified as a FlatBuffer:
/// for the farm merge, which rebuilds a level's `voxel_keys` from its shards' blocks.
pub(crate) fn stored_block_keys(stored: &[u8]) -> Result<Vec<u64>, String> {
    let inflated;
    let bytes = if super::is_coded(stored) {
        inflated = super::inflate_block(stored)?;
        &inflated[..]
    } else {
        stored
    };
    let block = flatbuffers::root_with_opts::<fb::Block>(&verifier_options(), bytes)
        .map_err(|e| format!("voxel block: {e}"))?;
    Ok(block
        .keys()
        .ok_or("a voxel block without keys")?
        .iter()
        .collect())
}

/// The padding after blob `b` up to the next blob is zero.
fn check_gap(data: &[u8], b: &Blob) -> Result<(), FormatError> {
    let from = (b.offset + b.size) as usize;
    if data[from..b.gap_end as usize].iter().any(|&x| x != 0) {
        return Err(corrupt(format!("non-zero padding at {from}")));
    }
    Ok(())
}

/// Whether a FlatBuffer blob carries this file identifier; false for one too short to hold an
/// identifier (flatbuffers asserts on those).
fn has_identifier(b: &[u8], id: &str) -> bool {
    b.len() >= flatbuffers::SIZE_UOFFSET + flatbuffers::FILE_IDENTIFIER_LENGTH
        && flatbuffers::buffer_has_identifier(b, id, false)
}

/// Verifies one block: checksum, identifier, FlatBuffers structure, the invariants the
/// accessors rely on, and the padding after it.
fn check_blob(
    data: &[u8],
    r: &Blob,
    settings: &RecordedSettings,
    levels: &[LevelInfo],
    checksums: bool,
    trees: bool,
    minor: u16,
) -> Result<Option<Box<[u8]>>, String> {
    let inner = || -> Result<Option<Box<[u8]>>, FormatError> {
        let stored = &data[r.offset as usize..(r.offset + r.size) as usize];
        if checksums && crc32fast::hash(stored) != r.crc32 {
            return Err(corrupt(format!("block at {}: checksum mismatch", r.offset)));
        }
        // From 1.5 a block may be one Zstandard frame holding its FlatBuffer.
        let compressed = super::is_coded(stored);
        if compressed && minor < 5 {
            return Err(corrupt(format!(
                "block at {}: compressed, in a file older than 1.5",
                r.offset
            )));
        }
        if stored.starts_with(&super::planar::PLANAR_MAGIC) && minor < 6 {
            return Err(corrupt(format!(
                "block at {}: in byte planes, in a file older than 1.6",
                r.offset
            )));
        }
        if stored.starts_with(&super::planar::DERIVED_MAGIC) && minor < 8 {
            return Err(corrupt(format!(
                "block at {}: in byte planes with derived fields left out, in a file older than 1.8",
                r.offset
            )));
        }
        let inflated = if compressed {
            Some(
                super::inflate_block(stored)
                    .map_err(|e| corrupt(format!("block at {}: {e}", r.offset)))?
                    .into_boxed_slice(),
            )
        } else {
            None
        };
        let b: &[u8] = inflated.as_deref().unwrap_or(stored);
        if !has_identifier(b, BLOCK_ID) {
            return Err(corrupt(format!("block at {}: wrong identifier", r.offset)));
        }
        let block = flatbuffers::root_with_opts::<fb::Block>(&verifier_options(), b)
            .map_err(|e| corrupt(format!("block at {}: {e}", r.offset)))?;
        match r.kind {
            BlobKind::Voxels(l) => {
                let res = levels[l as usize].grid.res;
                check_voxel_block(&block, r, l, res, settings.aiv_res, trees, minor)?;
            }
            BlobKind::Faces(l) => {
                let res = levels[l as usize].grid.res;
                check_face_block(&block, r, l, res, settings.abv_res, trees, minor)?;
            }
            BlobKind::Reserved => {}
        }
        check_gap(data, r)?;
        Ok(inflated)
    };
    inner().map_err(|e| match e {
        FormatError::Corrupt(s) => s,
        other => other.to_string(),
    })
}

fn check_voxel_block(
    b: &fb::Block,
    r: &Blob,
    level: u32,
    res: u32,
    aiv_res: u32,
    trees: bool,
    minor: u16,
) -> Result<u64, FormatError> {
    use super::quantize;
    let at = r.offset;
    let err = |s: &str| corrupt(format!("voxel block at {at}: {s}"));
    if b.level() != level {
        return Err(err("belongs to another level"));
    }
    let (Some(keys), Some(recs)) = (b.keys(), b.voxels()) else {
        return Err(err("missing arrays"));
    };
    // Each component in exactly one layout; the quantized ones from 1.4 on.
    let quantized =
        b.qlobes().is_some() || b.qmoments().is_some() || b.qdielectric_moments().is_some();
    if (quantized || b.aiv_qnodes().is_some()) && minor < 4 {
        return Err(err("quantized arrays in a file older than 1.4"));
    }
    let lobes = match (b.lobes(), b.qlobes()) {
        (Some(l), None) => Lobes::F32(l),
        (None, Some(q)) => Lobes::Q16(q),
        _ => return Err(err("lobes missing or in both layouts")),
    };
    let (n_moments, n_diel) = match (
        b.moments(),
        b.dielectric_moments(),
        b.qmoments(),
        b.qdielectric_moments(),
    ) {
        (Some(m), Some(d), None, None) => (m.len(), d.len()),
        (None, None, Some(m), Some(d)) => (m.len(), d.len()),
        _ => return Err(err("moments missing or in both layouts")),
    };
    let nodes = match (b.aiv_nodes(), b.aiv_qnodes()) {
        (Some(f), None) => Nodes::F32(f),
        (None, Some(q)) => Nodes::Q16(q),
        _ => return Err(err("AIV nodes missing or in both layouts")),
    };
    let n = keys.len();
    if recs.len() != n || n as u64 != r.count as u64 || n == 0 {
        return Err(err("voxel count mismatch"));
    }
    if keys.get(0) != r.first_key || keys.get(n - 1) != r.last_key {
        return Err(err("key range mismatch"));
    }
    if let Some(e) = b.exposure() {
        if e.len() != n || e.iter().any(|x| !(0.0625..=1.0).contains(&x)) {
            return Err(err("exposure not one value in [1/16, 1] per voxel"));
        }
    }
    for i in 0..n {
        let k = keys.get(i);
        if i > 0 && keys.get(i - 1) >= k {
            return Err(err("keys not ascending"));
        }
        let c = demorton3(k);
        if k >> 63 != 0 || c.max_element() >= res {
            return Err(err("key outside the level"));
        }
        let v = recs.get(i);
        let floats_ok = [
            v.area(),
            v.coverage(),
            v.roughness_mean(),
            v.roughness_variance(),
            v.aiv_scaling(),
        ]
        .iter()
        .all(|x| x.is_finite())
            && [v.center(), v.axis_x(), v.axis_y(), v.axis_z()]
                .iter()
                .all(|x| finite3(x));
        if !floats_ok {
            return Err(err("non-finite voxel field"));
        }
        let lobe_end = v.lobe_start() as u64 + v.lobe_count() as u64;
        if v.lobe_count() == 0 || v.lobe_count() > 16 || lobe_end > lobes.len() as u64 {
            return Err(err("lobe range"));
        }
        for j in v.lobe_start() as usize..lobe_end as usize {
            let ok = match lobes {
                Lobes::F32(f) => {
                    let l = f.get(j);
                    [l.weight(), l.alpha_x(), l.alpha_y()]
                        .iter()
                        .all(|x| x.is_finite())
                        && [l.t(), l.b(), l.n()].iter().all(|x| finite3(x))
                }
                Lobes::Q16(q) => quantize::lobe_ok(q.get(j)),
            };
            if !ok {
                return Err(err("non-finite or out-of-range lobe"));
            }
        }
        let directional = v.flags().contains(fb::VoxelFlags::DirectionalMoments);
        let mres = v.moment_res() as u64;
        let expected = if directional {
            if mres == 0 || mres > 64 {
                return Err(err("moment resolution"));
            }
            2 * mres * mres
        } else {
            1
        };
        let mend = v.moment_start() as u64 + v.moment_count() as u64;
        let metal = v.flags().contains(fb::VoxelFlags::Metallic);
        let avail = if metal { n_moments } else { n_diel } as u64;
        if v.moment_count() as u64 != expected || mend > avail {
            return Err(err("moment range"));
        }
        for j in v.moment_start() as usize..mend as usize {
            let ok = if let (true, Some(q)) = (metal, b.qmoments()) {
                quantize::moments_ok(q.get(j))
            } else if let (false, Some(q)) = (metal, b.qdielectric_moments()) {
                quantize::dielectric_moments_ok(q.get(j))
            } else if metal {
                let m = b.moments().expect("checked above").get(j);
                finite3(m.base())
                    && finite3(m.metal_base())
                    && [
                        m.specular(),
                        m.metal_specular(),
                        m.metallic(),
                        m.f90(),
                        m.metal_f90(),
                    ]
                    .iter()
                    .all(|x| x.is_finite())
            } else {
                let m = b.dielectric_moments().expect("checked above").get(j);
                finite3(m.base()) && m.specular().is_finite() && m.f90().is_finite()
            };
            if !ok {
                return Err(err("non-finite moments"));
            }
        }
        let tree = v.flags().contains(fb::VoxelFlags::AivTree);
        let aend = v.aiv_start() as u64 + v.aiv_count() as u64;
        if aend > nodes.len() as u64 || (tree != (v.aiv_count() > 0)) {
            return Err(err("AIV range"));
        }
        let s = v.aiv_start() as usize;
        if !trees {
            continue;
        }
        validate_tree(aiv_res, v.aiv_count() as usize, |j| nodes.shape(s + j))
            .map_err(|e| err(&format!("AIV tree: {e}")))?;
    }
    Ok(n as u64)
}

fn check_face_block(
    b: &fb::Block,
    r: &Blob,
    level: u32,
    res: u32,
    abv_res: u32,
    trees: bool,
    minor: u16,
) -> Result<u64, FormatError> {
    let at = r.offset;
    let err = |s: &str| corrupt(format!("face block at {at}: {s}"));
    if b.level() != level {
        return Err(err("belongs to another level"));
    }
    let Some(faces) = b.faces() else {
        return Err(err("missing arrays"));
    };
    let nodes = match (b.abv_nodes(), b.abv_qnodes()) {
        (Some(f), None) => Nodes::F32(f),
        (None, Some(q)) if minor >= 4 => Nodes::Q16(q),
        (None, Some(_)) => return Err(err("quantized arrays in a file older than 1.4")),
        _ => return Err(err("ABV nodes missing or in both layouts")),
    };
    if faces.len() as u64 != r.count as u64 {
        return Err(err("face count mismatch"));
    }
    for f in faces.iter() {
        if f.x() >= res || f.y() >= res || f.z() >= res || f.dir() >= 6 {
            return Err(err("face outside the level"));
        }
        if !f.abv_scaling().is_finite() {
            return Err(err("non-finite ABV"));
        }
        let end = f.abv_start() as u64 + f.abv_count() as u64;
        if end > nodes.len() as u64 {
            return Err(err("ABV range"));
        }
        let s = f.abv_start() as usize;
        if !trees {
            continue;
        }
        validate_tree(abv_res, f.abv_count() as usize, |j| nodes.shape(s + j))
            .map_err(|e| err(&format!("ABV tree: {e}")))?;
    }
    Ok(faces.len() as u64)
}

/// Reads everything a renderer or tool would read from a verified file (every voxel's
/// appearance, ellipsoid and visibility in a few directions, every face, lookups by key):
/// used by the fuzz target and the tests to show that a file that passed verification cannot
/// make an accessor panic.
pub fn exercise(agg: &Aggregate) -> usize {
    let dirs = [Vec3::X, Vec3::NEG_Y, Vec3::new(0.48, 0.6, -0.64)];
    let mut n = 0;
    for l in 0..agg.level_count() {
        let _ = agg.grid(l);
        let _ = agg.counts(l);
        let _ = agg.voxel_keys(l);
        for v in agg.voxels(l) {
            let _ = v.appearance();
            let _ = v.ellipsoid();
            for d in dirs {
                let _ = v.aiv(d);
            }
            let _ = agg.find_voxel(l, v.key);
            n += 1;
        }
        let _ = agg.find_voxel(l, 12345);
        n += agg.read_level(l).faces.len();
        for f in agg.faces(l) {
            for d in dirs {
                let _ = f.abv(d);
            }
        }
    }
    n
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::haar::{forward, quantize_tree, truncate};

    /// The integer walk of a fixed-point tree's bytes gives the value the generic walk gives
    /// on the same tree decoded to floats, in every cell of sparse trees of every size.
    #[test]
    fn fixed_point_walk_matches_the_decoded_tree() {
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        for n in [2usize, 4, 8, 16, 32, 64] {
            for keep in [0.05, 0.3, 1.0] {
                let map: Vec<f32> = (0..n * n).map(|_| next()).collect();
                let (scaling, mut details) = forward(&map, n);
                truncate(scaling, &mut details, keep, 1.0);
                let tree = SparseHaar::new(scaling, &details, n);
                let q = quantize_tree(&tree).expect("fits");
                let bytes: Vec<u8> = q
                    .iter()
                    .flat_map(|x| {
                        let l = x.links.to_le_bytes();
                        [l[0], l[1], x.q[0] as u8, x.q[1] as u8, x.q[2] as u8, 0]
                    })
                    .collect();
                let decoded = dequantize_tree(n as u32, scaling, &q);
                for y in 0..n as u32 {
                    for x in 0..n as u32 {
                        let a = eval_q16(n as u32, scaling, &bytes, x, y);
                        let b = decoded.eval(x, y);
                        assert!(
                            (a - b).abs() <= 1e-5,
                            "n {n} keep {keep} ({x}, {y}): {a} vs {b}"
                        );
                    }
                }
            }
        }
    }
}
