//! The non-standard 2D Haar wavelet transform (orthonormal), coefficient truncation, and an
//! implicit sparse quadtree that answers one pixel without decompressing (supplemental §3,
//! after Lalonde 1997), used for the aggregated visibility maps.
//!
//! On an N×N map (N = 2^n), each step replaces a 2×2 block (p00 p01 / p10 p11) of the current
//! average image by its average a = Σp/2 and three details h = (p00 − p01 + p10 − p11)/2,
//! v = (p00 + p01 − p10 − p11)/2, d = (p00 − p01 − p10 + p11)/2: an orthonormal change of basis,
//! so the squared coefficients add up to the map's energy and dropping the smallest ones is
//! the best truncation in L2. A pixel is then c/N + Σ over its ancestors (h·σx + v·σy +
//! d·σxσy)/s, with s the ancestor's block size and σ = ±1 the pixel's half within it.

/// Forward transform. Returns the scaling coefficient and the details of every quadtree node,
/// level by level from the root (level l has 4^l nodes in row-major order, 3 values each).
pub fn forward(map: &[f32], n: usize) -> (f32, Vec<[f32; 3]>) {
    assert!(
        n.is_power_of_two() && map.len() == n * n,
        "map must be N×N with N a power of two"
    );
    let mut cur: Vec<f64> = map.iter().map(|&v| v as f64).collect();
    let mut size = n;
    let mut levels: Vec<Vec<[f32; 3]>> = Vec::new();
    while size > 1 {
        let half = size / 2;
        let mut next = vec![0f64; half * half];
        let mut det = vec![[0f32; 3]; half * half];
        for y in 0..half {
            for x in 0..half {
                let p00 = cur[(2 * y) * size + 2 * x];
                let p01 = cur[(2 * y) * size + 2 * x + 1];
                let p10 = cur[(2 * y + 1) * size + 2 * x];
                let p11 = cur[(2 * y + 1) * size + 2 * x + 1];
                next[y * half + x] = (p00 + p01 + p10 + p11) / 2.0;
                det[y * half + x] = [
                    ((p00 - p01 + p10 - p11) / 2.0) as f32,
                    ((p00 + p01 - p10 - p11) / 2.0) as f32,
                    ((p00 - p01 - p10 + p11) / 2.0) as f32,
                ];
            }
        }
        levels.push(det);
        cur = next;
        size = half;
    }
    levels.reverse();
    (cur[0] as f32, levels.into_iter().flatten().collect())
}

/// Inverse transform of (scaling, details) into an N×N map.
pub fn inverse(scaling: f32, details: &[[f32; 3]], n: usize) -> Vec<f32> {
    let mut cur = vec![scaling as f64];
    let mut size = 1;
    let mut offset = 0;
    while size < n {
        let mut next = vec![0f64; 4 * size * size];
        for y in 0..size {
            for x in 0..size {
                let a = cur[y * size + x];
                let [h, v, d] = details[offset + y * size + x].map(|c| c as f64);
                let w = 2 * size;
                next[(2 * y) * w + 2 * x] = (a + h + v + d) / 2.0;
                next[(2 * y) * w + 2 * x + 1] = (a - h + v - d) / 2.0;
                next[(2 * y + 1) * w + 2 * x] = (a + h - v - d) / 2.0;
                next[(2 * y + 1) * w + 2 * x + 1] = (a - h - v + d) / 2.0;
            }
        }
        offset += size * size;
        cur = next;
        size *= 2;
    }
    cur.into_iter().map(|v| v as f32).collect()
}

/// Zeroes all but the largest-magnitude detail coefficients: at most `keep` (a fraction of the
/// N² coefficients, the scaling one always kept), and fewer when fewer already hold `energy`
/// (a fraction) of the details' energy — the map's variance. (Counting the scaling coefficient
/// in the energy would let a bright map's mean alone pass 95% and drop every edge.) Returns the
/// number of details kept.
pub fn truncate(_scaling: f32, details: &mut [[f32; 3]], keep: f32, energy: f32) -> usize {
    let total: f64 = details
        .iter()
        .flatten()
        .map(|c| (*c as f64).powi(2))
        .sum::<f64>();
    let mut mags: Vec<(f32, usize, usize)> = details
        .iter()
        .enumerate()
        .flat_map(|(i, d)| d.iter().enumerate().map(move |(k, c)| (c.abs(), i, k)))
        .filter(|x| x.0 > 0.0)
        .collect();
    mags.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    let n2 = details.len() * 3 + 1;
    let cap = ((keep.clamp(0.0, 1.0) * n2 as f32).ceil() as usize).saturating_sub(1);
    let mut acc = 0f64;
    let mut kept = 0;
    for m in &mags {
        if kept >= cap || (total > 0.0 && acc >= energy as f64 * total) {
            break;
        }
        acc += (m.0 as f64).powi(2);
        kept += 1;
    }
    for m in &mags[kept..] {
        details[m.1][m.2] = 0.0;
    }
    kept
}

/// Wavelet shrinkage before truncation (Donoho and Johnstone's universal threshold): zeroes
/// the details below σ·√(2 ln N²), where σ is the standard deviation of the Monte Carlo noise
/// of one pixel. Orthonormal Haar maps white pixel noise to white coefficient noise of the
/// same σ, so what this removes is, with high probability, noise alone; the paper's
/// "keep 10%, fewer while 95% of the energy stays" would otherwise spend its budget on noise
/// in maps estimated from a ray or two per pixel. Returns the number of details zeroed.
pub fn shrink(details: &mut [[f32; 3]], sigma: f32, n: usize) -> usize {
    if !(sigma > 0.0) || n < 2 {
        return 0;
    }
    let lambda = sigma * (2.0 * ((n * n) as f32).ln()).sqrt();
    let mut zeroed = 0;
    for d in details.iter_mut().flatten() {
        if *d != 0.0 && d.abs() < lambda {
            *d = 0.0;
            zeroed += 1;
        }
    }
    zeroed
}

/// A node of the sparse quadtree (depth-first preorder).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Node {
    /// The three detail coefficients (horizontal, vertical, diagonal) of the node's 2×2 block.
    pub details: [f32; 3],
    /// Bit q set: child quadrant q (0 top-left, 1 top-right, 2 bottom-left, 3 bottom-right)
    /// is present.
    pub children: u8,
    /// Nodes in this node's subtree, itself included (for skipping siblings).
    pub subtree: u32,
}

/// The implicit sparse quadtree of a truncated map.
#[derive(Clone, Debug, PartialEq)]
pub struct SparseHaar {
    /// Side N of the map in cells (a power of two).
    pub n: u32,
    /// The scaling coefficient c (the map's mean is c / N).
    pub scaling: f32,
    /// Preorder; empty when every detail is zero (a constant map).
    pub nodes: Vec<Node>,
}

impl SparseHaar {
    /// Builds the tree of non-zero details (a node exists when it or a descendant has one).
    pub fn new(scaling: f32, details: &[[f32; 3]], n: usize) -> Self {
        // Level offsets.
        let mut offsets = vec![0usize];
        let mut s = 1;
        while s < n {
            offsets.push(offsets.last().unwrap() + s * s);
            s *= 2;
        }
        let depth = offsets.len() - 1;
        fn build(
            l: usize,
            x: usize,
            y: usize,
            depth: usize,
            offsets: &[usize],
            details: &[[f32; 3]],
            out: &mut Vec<Node>,
        ) -> bool {
            if l >= depth {
                return false;
            }
            let size = 1 << l;
            let d = details[offsets[l] + y * size + x];
            let at = out.len();
            out.push(Node {
                details: d,
                children: 0,
                subtree: 1,
            });
            let mut mask = 0u8;
            for q in 0..4 {
                if build(
                    l + 1,
                    2 * x + (q & 1),
                    2 * y + (q >> 1),
                    depth,
                    offsets,
                    details,
                    out,
                ) {
                    mask |= 1 << q;
                }
            }
            if mask == 0 && d == [0.0; 3] {
                out.truncate(at);
                return false;
            }
            out[at].children = mask;
            out[at].subtree = (out.len() - at) as u32;
            true
        }
        let mut nodes = Vec::new();
        build(0, 0, 0, depth, &offsets, details, &mut nodes);
        SparseHaar {
            n: n as u32,
            scaling,
            nodes,
        }
    }

    /// The tree with only the details `keep` accepts (a detail's node and its level's block
    /// size `s`, the map's side at the root, halving per level), nodes left without a detail
    /// or a child pruned: what [`Self::new`] builds from the dense details with the others
    /// zeroed. The rate control's truncation (`bake::rate`) keeps a detail when its weighted
    /// energy reaches the level's Lagrange multiplier.
    pub fn retain(&self, keep: impl Fn(f32, u32) -> bool) -> SparseHaar {
        fn walk(
            src: &[Node],
            i: usize,
            size: u32,
            keep: &dyn Fn(f32, u32) -> bool,
            out: &mut Vec<Node>,
        ) -> bool {
            let nd = src[i];
            let details = nd
                .details
                .map(|c| if c != 0.0 && keep(c, size) { c } else { 0.0 });
            let at = out.len();
            out.push(Node {
                details,
                children: 0,
                subtree: 1,
            });
            let (mut mask, mut j) = (0u8, i + 1);
            for q in 0..4 {
                if nd.children & (1 << q) != 0 {
                    if walk(src, j, size / 2, keep, out) {
                        mask |= 1 << q;
                    }
                    j += src[j].subtree as usize;
                }
            }
            if mask == 0 && details == [0.0; 3] {
                out.truncate(at);
                return false;
            }
            out[at].children = mask;
            out[at].subtree = (out.len() - at) as u32;
            true
        }
        let mut nodes = Vec::with_capacity(self.nodes.len());
        if !self.nodes.is_empty() {
            walk(&self.nodes, 0, self.n, &keep, &mut nodes);
        }
        SparseHaar {
            n: self.n,
            scaling: self.scaling,
            nodes,
        }
    }

    /// Every non-zero detail of the tree, in preorder.
    pub fn details(&self) -> impl Iterator<Item = f32> + '_ {
        self.nodes
            .iter()
            .flat_map(|n| n.details)
            .filter(|&c| c != 0.0)
    }

    /// Whether the map is constant (no details): visibility then needs a flag, not a tree.
    pub fn is_constant(&self) -> bool {
        self.nodes.is_empty()
    }

    /// The value of pixel (x, y), walking one root-to-leaf path.
    pub fn eval(&self, x: u32, y: u32) -> f32 {
        eval_tree(
            self.n,
            self.scaling,
            self.nodes.len(),
            |i, _| self.nodes[i],
            x,
            y,
        )
    }
}

/// The value of pixel (x, y) of the `n × n` map whose tree has `len` nodes given by `node`
/// (preorder), walking one root-to-leaf path: the storage-independent form of
/// [`SparseHaar::eval`], used on trees read zero-copy from a file. `node(i, s)` is node `i`,
/// whose block is `s` pixels wide (fixed-point storage, [`QNode`], needs it to scale the
/// details). The tree must have passed [`validate_tree`] (or be built by [`SparseHaar::new`]).
#[inline]
pub fn eval_tree(
    n: u32,
    scaling: f32,
    len: usize,
    node: impl Fn(usize, u32) -> Node,
    x: u32,
    y: u32,
) -> f32 {
    let n = n.max(1);
    let mut v = scaling as f64 / n as f64;
    let mut i = 0usize;
    let mut size = n;
    let (mut x0, mut y0) = (0u32, 0u32);
    while i < len && size > 1 {
        let nd = node(i, size);
        let half = size / 2;
        let right = x >= x0 + half;
        let bottom = y >= y0 + half;
        let sx = if right { -1.0 } else { 1.0 };
        let sy = if bottom { -1.0 } else { 1.0 };
        let [h, vv, d] = nd.details.map(|c| c as f64);
        v += (h * sx + vv * sy + d * sx * sy) / size as f64;
        let q = (right as u8) | ((bottom as u8) << 1);
        if nd.children & (1 << q) == 0 {
            break;
        }
        // Skip the subtrees of earlier present siblings.
        let mut j = i + 1;
        for p in 0..q {
            if nd.children & (1 << p) != 0 && j < len {
                j += node(j, half).subtree as usize;
            }
        }
        i = j;
        if right {
            x0 += half;
        }
        if bottom {
            y0 += half;
        }
        size = half;
    }
    v as f32
}

/// Checks that `len` nodes form a well-shaped preorder tree for an `n × n` map: subtree sizes
/// add up, children stop at the finest level, every coefficient is finite. A tree that passes
/// can be walked by [`eval_tree`] without reading out of range.
pub fn validate_tree(n: u32, len: usize, node: impl Fn(usize) -> Node) -> Result<(), String> {
    if len == 0 {
        return Ok(());
    }
    if !n.is_power_of_two() || n < 2 {
        return Err(format!("tree for a {n}x{n} map"));
    }
    let depth = n.trailing_zeros() as usize;
    if depth > 16 {
        return Err(format!("tree for a {n}x{n} map"));
    }
    // Iterative preorder walk: (node index, level), on a fixed stack (at most three pending
    // siblings per level), allocating nothing: blocks are verified on first read, while a
    // render waits.
    let mut stack = [(0usize, 0usize); 4 * 17];
    let mut top = 1usize;
    let mut visited = 0usize;
    while top > 0 {
        top -= 1;
        let (i, l) = stack[top];
        if i >= len {
            return Err(format!("node {i} out of {len}"));
        }
        visited += 1;
        if visited > len {
            return Err("nodes visited twice".into());
        }
        let nd = node(i);
        if !nd.details.iter().all(|c| c.is_finite()) {
            return Err(format!("node {i}: non-finite coefficient"));
        }
        if nd.children > 15 || (l + 1 >= depth && nd.children != 0) {
            return Err(format!("node {i}: bad child mask {}", nd.children));
        }
        let mut j = i + 1;
        let mut kids = [0usize; 4];
        let mut nk = 0;
        for q in 0..4 {
            if nd.children & (1 << q) != 0 {
                if j >= len {
                    return Err(format!("node {i}: child beyond the tree"));
                }
                kids[nk] = j;
                nk += 1;
                j = j
                    .checked_add(node(j).subtree as usize)
                    .ok_or("subtree size overflow")?;
            }
        }
        if j - i != nd.subtree as usize {
            return Err(format!(
                "node {i}: subtree size {} but children span {}",
                nd.subtree,
                j - i
            ));
        }
        for &k in kids[..nk].iter().rev() {
            if top >= stack.len() {
                return Err("tree deeper than its map".into());
            }
            stack[top] = (k, l + 1);
            top += 1;
        }
    }
    if node(0).subtree as usize != len {
        return Err(format!("root spans {} of {len} nodes", node(0).subtree));
    }
    Ok(())
}

/// Fixed-point scale of format 1.4's quantized details ([`QNode`]): a detail h of a node whose
/// block is s pixels wide is stored as round(h / s · 254) in a signed byte. By the transform's
/// normalisation h / s is a half-difference of quadrant means, within ±1/2 for a map in
/// [0, 1], so ±127 spans exactly the range a visibility needs. 16 bits were measured too (the
/// maple at 64³: 4e-5 at most); 8 bits give 0.012 at most and 0.002 RMS, far below the
/// maps' Monte Carlo noise, for 6 bytes a node instead of 8 (tools/src/bin/requantize.rs).
pub const Q_DETAIL: f32 = 254.0;

/// Most nodes a quantized subtree count (12 bits) holds: a full tree of a 64² map has 1365.
pub const Q_MAX_SUBTREE: u32 = 4095;

/// A node in format 1.4's fixed point (the schema's `QHaarNode`): the three details as
/// round(h / s · [`Q_DETAIL`]) and the links, subtree count in bits 0–11 and child mask in
/// bits 12–15. Per pixel the error is at most 3 · depth / (2 · 254): 0.035 on a 64² map.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct QNode {
    /// The three details in fixed point.
    pub q: [i8; 3],
    /// Subtree count (bits 0–11) and child mask (bits 12–15).
    pub links: u16,
}

impl QNode {
    /// The node of a block `size` pixels wide, in fixed point; `None` when its subtree is too
    /// large for 12 bits. Details saturate at ±1/2 of a pixel (never reached by a map in
    /// [0, 1]).
    pub fn quantize(n: &Node, size: u32) -> Option<QNode> {
        if n.subtree > Q_MAX_SUBTREE || n.children > 15 {
            return None;
        }
        let k = Q_DETAIL / size.max(1) as f32;
        let q = n.details.map(|d| {
            let x = (d * k).round();
            // NaN (never produced by the bake) maps to 0, like every non-finite coefficient.
            if x.is_nan() {
                0
            } else {
                x.clamp(-127.0, 127.0) as i8
            }
        });
        Some(QNode {
            q,
            links: n.subtree as u16 | (n.children as u16) << 12,
        })
    }

    /// The child mask.
    #[inline]
    pub fn children(&self) -> u8 {
        (self.links >> 12) as u8
    }

    /// Nodes in the subtree, itself included.
    #[inline]
    pub fn subtree(&self) -> u32 {
        (self.links & 0x0fff) as u32
    }

    /// The node of a block `size` pixels wide, decoded.
    #[inline]
    pub fn node(&self, size: u32) -> Node {
        let k = size as f32 / Q_DETAIL;
        Node {
            details: self.q.map(|q| q as f32 * k),
            children: self.children(),
            subtree: self.subtree(),
        }
    }
}

/// The block width of each node of a well-shaped preorder tree of an `n × n` map (`n` for
/// the root, halving per level), from each node's child mask and subtree count. Nodes the walk
/// never reaches (only in a malformed tree) keep width 1.
pub fn node_sizes(n: u32, len: usize, links: impl Fn(usize) -> (u8, u32)) -> Vec<u32> {
    let mut sizes = vec![1u32; len];
    let mut stack = vec![(0usize, n)];
    while let Some((i, s)) = stack.pop() {
        if i >= len || s < 2 {
            continue;
        }
        sizes[i] = s;
        let (children, _) = links(i);
        let mut j = i + 1;
        for q in 0..4 {
            if children & (1 << q) != 0 && j < len {
                stack.push((j, s / 2));
                j += links(j).1.max(1) as usize;
            }
        }
    }
    sizes
}

/// A tree in format 1.4's fixed point; `None` when it does not fit (a map above 64²).
pub fn quantize_tree(t: &SparseHaar) -> Option<Vec<QNode>> {
    let sizes = node_sizes(t.n, t.nodes.len(), |i| {
        (t.nodes[i].children, t.nodes[i].subtree)
    });
    t.nodes
        .iter()
        .zip(&sizes)
        .map(|(nd, &s)| QNode::quantize(nd, s))
        .collect()
}

/// A fixed-point tree of an `n × n` map with scaling coefficient `scaling`, decoded.
pub fn dequantize_tree(n: u32, scaling: f32, q: &[QNode]) -> SparseHaar {
    let sizes = node_sizes(n, q.len(), |i| (q[i].children(), q[i].subtree()));
    SparseHaar {
        n,
        scaling,
        nodes: q.iter().zip(&sizes).map(|(x, &s)| x.node(s)).collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smooth map observed through one Bernoulli draw per pixel (the ABV at one ray per
    /// cell): shrinkage then truncation is closer to the true map than truncation alone, and
    /// keeps far fewer coefficients.
    #[test]
    fn shrinkage_removes_noise_not_signal() {
        let n = 64;
        let truth: Vec<f32> = (0..n * n)
            .map(|i| {
                let (x, y) = ((i % n) as f32 / n as f32, (i / n) as f32 / n as f32);
                if x + 0.3 * y < 0.6 {
                    0.9
                } else {
                    0.2
                }
            })
            .collect();
        let mut rng = crate::math::rng::Pcg32::new(9, 9);
        let noisy: Vec<f32> = truth
            .iter()
            .map(|&p| if rng.next_f32() < p { 1.0 } else { 0.0 })
            .collect();
        let mean = noisy.iter().sum::<f32>() / noisy.len() as f32;
        let sigma = (mean * (1.0 - mean)).sqrt();
        let err = |shrunk: bool| {
            let (c, mut d) = forward(&noisy, n);
            if shrunk {
                shrink(&mut d, sigma, n);
            }
            let kept = truncate(c, &mut d, 0.10, 0.95);
            let m = inverse(c, &d, n);
            let e = (m
                .iter()
                .zip(&truth)
                .map(|(a, b)| (a - b).powi(2))
                .sum::<f32>()
                / (n * n) as f32)
                .sqrt();
            (e, kept)
        };
        let ((e0, k0), (e1, k1)) = (err(false), err(true));
        assert!(e1 < 0.8 * e0, "shrunk {e1} vs {e0}");
        assert!(k1 * 4 < k0, "kept {k1} vs {k0}");
    }
    use crate::math::rng::Pcg32;

    fn random_map(n: usize, seed: u64) -> Vec<f32> {
        let mut r = Pcg32::new(seed, 1);
        (0..n * n)
            .map(|i| if (i / 7) % 3 == 0 { 1.0 } else { r.next_f32() })
            .collect()
    }

    /// `retain` on a tree is `new` on the dense details with the rejected ones zeroed,
    /// node for node (pruning included), and it tells each detail its level's block size.
    #[test]
    fn retain_is_new_on_the_kept_details() {
        let n = 32;
        let m = random_map(n, 11);
        let (c, d) = forward(&m, n);
        let full = SparseHaar::new(c, &d, n);
        for t in [0.0f32, 0.05, 0.2, 0.6, 10.0] {
            // Finer blocks need larger details: the rule depends on the size it is told.
            let rule = |v: f32, s: u32| v.abs() * (s as f32).sqrt() >= t;
            let mut dense = d.clone();
            let (mut offset, mut size) = (0usize, 1usize);
            while size < n {
                for x in &mut dense[offset..offset + size * size] {
                    for v in x.iter_mut() {
                        if !rule(*v, (n / size) as u32) {
                            *v = 0.0;
                        }
                    }
                }
                offset += size * size;
                size *= 2;
            }
            assert_eq!(full.retain(rule), SparseHaar::new(c, &dense, n), "t = {t}");
        }
        assert!(full.retain(|_, _| false).is_constant());
        assert_eq!(
            full.details().count(),
            d.iter().flatten().filter(|&&v| v != 0.0).count()
        );
    }

    #[test]
    fn round_trip_and_parseval() {
        for n in [1usize, 2, 8, 32] {
            let m = random_map(n, n as u64);
            let (c, d) = forward(&m, n);
            let back = inverse(c, &d, n);
            for (a, b) in m.iter().zip(&back) {
                assert!((a - b).abs() < 1e-5);
            }
            let e_map: f64 = m.iter().map(|v| (*v as f64).powi(2)).sum();
            let e_coef: f64 =
                (c as f64).powi(2) + d.iter().flatten().map(|v| (*v as f64).powi(2)).sum::<f64>();
            assert!((e_map - e_coef).abs() < 1e-4 * e_map.max(1.0));
        }
    }

    #[test]
    fn sparse_tree_answers_single_pixels() {
        let n = 32;
        let m = random_map(n, 5);
        let (c, mut d) = forward(&m, n);
        let full = SparseHaar::new(c, &d, n);
        for y in 0..n as u32 {
            for x in 0..n as u32 {
                assert!((full.eval(x, y) - m[(y * n as u32 + x) as usize]).abs() < 1e-4);
            }
        }
        let kept = truncate(c, &mut d, 0.10, 0.95);
        assert!(kept + 1 <= (0.10 * (n * n) as f32).ceil() as usize);
        let t = SparseHaar::new(c, &d, n);
        let rec = inverse(c, &d, n);
        for y in 0..n as u32 {
            for x in 0..n as u32 {
                assert!((t.eval(x, y) - rec[(y * n as u32 + x) as usize]).abs() < 1e-4);
            }
        }
        assert!(t.nodes.len() < full.nodes.len());
    }

    #[test]
    fn truncation_keeps_energy_or_cap() {
        let n = 16;
        // A smooth map: few coefficients hold 95% of the energy, so fewer than 10% are kept.
        let m: Vec<f32> = (0..n * n).map(|i| 0.5 + 0.01 * ((i % n) as f32)).collect();
        let (c, mut d) = forward(&m, n);
        let before: f64 = d.iter().flatten().map(|v| (*v as f64).powi(2)).sum();
        let kept = truncate(c, &mut d, 0.10, 0.95);
        let after: f64 = d.iter().flatten().map(|v| (*v as f64).powi(2)).sum();
        assert!(after >= 0.95 * before && kept < 26, "kept {kept}");
        // A hard edge (a silhouette) in a bright map: by Parseval the squared error is the
        // dropped detail energy, at most 5% of the details' (the mean does not count).
        let edge: Vec<f32> = (0..n * n)
            .map(|i| if i % n < 5 { 0.0 } else { 1.0 })
            .collect();
        let (c, mut d) = forward(&edge, n);
        let e_d: f64 = d.iter().flatten().map(|v| (*v as f64).powi(2)).sum();
        let kept = truncate(c, &mut d, 1.0, 0.95);
        assert!(kept > 0, "the edge keeps details");
        let rec = inverse(c, &d, n);
        let se: f64 = edge
            .iter()
            .zip(&rec)
            .map(|(a, b)| ((a - b) as f64).powi(2))
            .sum();
        assert!(se <= 0.05 * e_d + 1e-6, "{se} > 5% of {e_d}");
        // Constant maps are flags.
        let (c, d) = forward(&vec![1.0; 64], 8);
        let t = SparseHaar::new(c, &d, 8);
        assert!(t.is_constant() && (t.eval(3, 5) - 1.0).abs() < 1e-6);
    }

    /// Fixed point: every pixel of a quantized tree within 3 · depth / (2 · 254) of the
    /// float tree's (the bound [`QNode`] states), full and truncated, and the same structure.
    #[test]
    fn quantized_trees_stay_within_their_bound() {
        for n in [2usize, 8, 32, 64] {
            let m = random_map(n, 11 + n as u64);
            let (c, mut d) = forward(&m, n);
            for truncated in [false, true] {
                if truncated {
                    truncate(c, &mut d, 0.10, 0.95);
                }
                let t = SparseHaar::new(c, &d, n);
                let q = quantize_tree(&t).expect("fits");
                let back = dequantize_tree(n as u32, c, &q);
                assert_eq!(back.nodes.len(), t.nodes.len());
                let bound = 3.0 * n.trailing_zeros() as f32 / (2.0 * Q_DETAIL) + 1e-6;
                for y in 0..n as u32 {
                    for x in 0..n as u32 {
                        let e = (back.eval(x, y) - t.eval(x, y)).abs();
                        assert!(e <= bound, "{n}² ({x}, {y}): {e} > {bound}");
                        let via = eval_tree(n as u32, c, q.len(), |i, s| q[i].node(s), x, y);
                        assert_eq!(via, back.eval(x, y));
                    }
                }
                assert!(validate_tree(n as u32, q.len(), |i| q[i].node(1)).is_ok());
            }
        }
        // A map above 64² does not fit 12-bit subtree counts.
        let m = random_map(128, 3);
        let (c, d) = forward(&m, 128);
        assert!(quantize_tree(&SparseHaar::new(c, &d, 128)).is_none());
    }
}
