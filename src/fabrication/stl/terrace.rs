//! Exact meshing of a terraced (quantized) height map.
//!
//! Every pixel is a flat square at its height. Work on the lattice of pixel corners
//! (row `r` in `0..=rows`, column `c` in `0..=cols`), with "outside" as one more value around
//! the map:
//!
//! 1. **Key points.** A corner is a key point unless its four pixels (top-left TL, TR, BL, BR)
//!    form a straight configuration: all equal, or TL = TR and BL = BR (a horizontal boundary or
//!    none), or TL = BL and TR = BR (a vertical one). So the four map corners, every turn and
//!    junction of a boundary, and every point of the outline where the height changes are key.
//! 2. **Boundary segments.** Between consecutive key points of one lattice row (or column) the
//!    unit edges are either all boundaries with one constant pair of heights, or none (a
//!    non-key corner is straight); each boundary run is one segment.
//! 3. **Top.** One constrained Delaunay triangulation (spade) of all key points with all
//!    segments as constraints. Every triangle lies inside one terrace, whose height is read at
//!    its centroid. Triangles of neighbouring terraces share the segment end points exactly.
//! 4. **Walls.** Each segment between heights a < b gets a vertical wall from a to b, facing
//!    the lower side; segments on the outline get side walls from the base up. At each end the
//!    vertical edge is split at every height of the pixels around that key point lying strictly
//!    between the wall's bottom and top, so that neighbouring walls share edges exactly (no
//!    T-junctions); the wall is triangulated as a zipper between its two vertical chains.
//! 5. **Base.** A fan from the centre of the base plane to the outline's key points.
//!
//! **Saddles.** Around a corner the four walls between cyclically adjacent pixels cover each
//! height interval an even number of times; four times (four faces on one edge: not a
//! manifold) exactly when the diagonals are separated, both pixels of one diagonal lower than
//! both of the other (a checkerboard, or e.g. TL = 0, TR = 3, BR = 1, BL = 2). Such a corner is
//! resolved by a chamfer: the corner of TR is cut by the segment from `A = (c, r - d)` to
//! `B = (c + d, r)` (lattice units, `d` = [`CHAMFER_FRACTION`]) and the little triangle joins
//! BR's terrace. The corner then sees three terraces (TL, BR, BL) and A sees three (TL, TR, BR),
//! which no wall arrangement can make non-manifold; where TL differs from BR a short wall
//! from A down to the corner separates them. Each pixel is cut at most at its bottom-left
//! corner, so the surface stays exact elsewhere.
//!
//! Orientation: lattice `(c, r)` maps to the plane `(X, Y) = (c, -r)`, right-handed with Z up;
//! spade returns counter-clockwise faces, so top triangles face up; walls are oriented with
//! the lower side on their right, the base faces down.

use std::collections::HashMap;

use spade::{ConstrainedDelaunayTriangulation, Point2, Triangulation};

use super::mesh::{Frame, Mesh, SurfaceKind};
use crate::error::{Error, Resource, Result};
use crate::grid::Grid;

/// Leg of the saddle chamfer as a fraction of the pitch (1/64: exact in binary, and large
/// enough to stay clearly resolved after rounding to `f32` for parts up to several centimetres).
pub const CHAMFER_FRACTION: f64 = 1.0 / 64.0;

/// The value of "outside the map".
const OUT: u16 = u16::MAX;
const NONE: u32 = u32::MAX;
/// Chain key of the base plane (below every level).
const BASE: i32 = -1;

#[derive(Debug, Clone, Copy)]
struct Saddle {
    /// The key point at the corner.
    kp: u32,
    r: u32,
    c: u32,
    /// Pixel levels TL, TR, BL, BR.
    quad: [u16; 4],
}

impl Saddle {
    /// Level of the chamfer triangle cut from TR (that of BR).
    fn joined(&self) -> u16 {
        self.quad[3]
    }
}

/// The distinct levels of the pixels around a point (sorted ascending) and whether the point
/// lies on the outline (then it also carries a base vertex).
#[derive(Debug, Clone, Copy)]
struct Corner {
    lv: [u16; 4],
    n: u8,
    base: bool,
}

impl Corner {
    fn new(vals: &[u16]) -> Corner {
        let mut lv = [0u16; 4];
        let mut n = 0;
        let mut base = false;
        for &v in vals {
            if v == OUT {
                base = true;
            } else if !lv[..n].contains(&v) {
                lv[n] = v;
                n += 1;
            }
        }
        lv[..n].sort_unstable();
        Corner { lv, n: n as u8, base }
    }
    fn levels(&self) -> &[u16] {
        &self.lv[..self.n as usize]
    }
    fn vertex_count(&self) -> u32 {
        self.n as u32 + self.base as u32
    }
}

/// A boundary run from point `p` to point `q` with the levels on its left and right (as seen
/// in the `(X, Y)` plane walking from p to q); `OUT` for outside.
#[derive(Debug, Clone, Copy)]
struct Segment {
    p: u32,
    q: u32,
    left: u16,
    right: u16,
}

/// Maps heights to level indices sorted by height. Returns (index per pixel, row-major;
/// height per level).
fn level_indices(heights: &Grid) -> Result<(Vec<u16>, Vec<f64>)> {
    let values = heights.values();
    let mut idx = Vec::with_capacity(values.len());
    let mut table: Vec<f64> = Vec::new();
    let mut map: HashMap<u64, u16> = HashMap::new();
    // NaN bits never match a (checked finite) height.
    let mut last = (f64::NAN.to_bits(), 0u16);
    for &v in values.iter() {
        let bits = if v == 0.0 { 0 } else { v.to_bits() };
        if bits != last.0 {
            let k = match map.get(&bits) {
                Some(&k) => k,
                None => {
                    if table.len() >= OUT as usize {
                        return Err(Error::limit(
                            Resource::Heights,
                            (table.len() + 1) as f64,
                            f64::from(OUT),
                            format!(
                                "terrace meshing supports at most {} distinct heights; \
                                 mesh a continuous map as a heightfield",
                                OUT
                            ),
                        ));
                    }
                    let k = table.len() as u16;
                    table.push(if v == 0.0 { 0.0 } else { v });
                    map.insert(bits, k);
                    k
                }
            };
            last = (bits, k);
        }
        idx.push(last.1);
    }
    let mut order: Vec<u16> = (0..table.len() as u16).collect();
    order.sort_by(|&a, &b| table[a as usize].total_cmp(&table[b as usize]));
    let mut rank = vec![0u16; table.len()];
    for (r, &k) in order.iter().enumerate() {
        rank[k as usize] = r as u16;
    }
    for v in idx.iter_mut() {
        *v = rank[*v as usize];
    }
    Ok((idx, order.iter().map(|&k| table[k as usize]).collect()))
}

/// The traced map: levels, key points and saddles.
struct Terraces {
    nr: usize,
    nc: usize,
    idx: Vec<u16>,
    /// Key points `(r, c)`, row-major.
    kps: Vec<[u32; 2]>,
    /// `kps[row_start[r]..row_start[r + 1]]` lie on lattice row r.
    row_start: Vec<u32>,
    /// Saddle index per key point, `NONE` if it is no saddle.
    saddle_of: Vec<u32>,
    saddles: Vec<Saddle>,
    /// Levels around each point: key points, then per saddle its chamfer points A and B.
    corners: Vec<Corner>,
}

impl Terraces {
    /// Level of pixel (r, c), `OUT` outside the map.
    fn px(&self, r: isize, c: isize) -> u16 {
        if r < 0 || c < 0 || r >= self.nr as isize || c >= self.nc as isize {
            OUT
        } else {
            self.idx[r as usize * self.nc + c as usize]
        }
    }

    fn trace(idx: Vec<u16>, nr: usize, nc: usize) -> Terraces {
        let mut kps: Vec<[u32; 2]> = Vec::new();
        let mut corners: Vec<Corner> = Vec::new();
        let mut row_start = Vec::with_capacity(nr + 2);
        let mut saddle_of: Vec<u32> = Vec::new();
        let mut saddles: Vec<Saddle> = Vec::new();
        // Pixel rows above and below the lattice row, padded with OUT on both sides.
        let mut above = vec![OUT; nc + 2];
        let mut below = vec![OUT; nc + 2];
        for r in 0..=nr {
            std::mem::swap(&mut above, &mut below);
            if r < nr {
                below[1..=nc].copy_from_slice(&idx[r * nc..(r + 1) * nc]);
            } else {
                below.fill(OUT);
            }
            row_start.push(kps.len() as u32);
            for c in 0..=nc {
                let (tl, tr, bl, br) = (above[c], above[c + 1], below[c], below[c + 1]);
                if (tl == tr && bl == br) || (tl == bl && tr == br) {
                    continue;
                }
                // Separated diagonals (level indices are sorted by height). On the outline two
                // edge-adjacent quadrants are outside, one on each diagonal, so this only
                // happens inside the map.
                let saddle = tl.max(br) < tr.min(bl) || tr.max(bl) < tl.min(br);
                if saddle {
                    // TR no longer touches the corner: its corner belongs to BR now.
                    corners.push(Corner::new(&[tl, bl, br]));
                    saddle_of.push(saddles.len() as u32);
                    saddles.push(Saddle {
                        kp: kps.len() as u32,
                        r: r as u32,
                        c: c as u32,
                        quad: [tl, tr, bl, br],
                    });
                } else {
                    corners.push(Corner::new(&[tl, tr, bl, br]));
                    saddle_of.push(NONE);
                }
                kps.push([r as u32, c as u32]);
            }
        }
        row_start.push(kps.len() as u32);
        for s in &saddles {
            let [tl, tr, _, br] = s.quad;
            // A on the vertical edge between TL and TR, next to the chamfer triangle (BR's);
            // B on the horizontal edge between TR and BR.
            corners.push(Corner::new(&[tl, tr, br]));
            corners.push(Corner::new(&[tr, br]));
        }
        Terraces { nr, nc, idx, kps, row_start, saddle_of, saddles, corners }
    }

    fn chamfer_a(&self, s: u32) -> u32 {
        (self.kps.len() + 2 * s as usize) as u32
    }
    fn chamfer_b(&self, s: u32) -> u32 {
        (self.kps.len() + 2 * s as usize + 1) as u32
    }

    /// Lattice position `(c, r)` of a point.
    fn position(&self, p: usize) -> [f64; 2] {
        if p < self.kps.len() {
            let [r, c] = self.kps[p];
            return [c as f64, r as f64];
        }
        let s = &self.saddles[(p - self.kps.len()) / 2];
        let (r, c) = (s.r as f64, s.c as f64);
        let d = CHAMFER_FRACTION;
        if (p - self.kps.len()).is_multiple_of(2) {
            [c, r - d]
        } else {
            [c + d, r]
        }
    }

    /// The key point at lattice (r, c), if any.
    fn kp_at(&self, r: usize, c: usize) -> Option<usize> {
        if r > self.nr {
            return None;
        }
        let (a, b) = (self.row_start[r] as usize, self.row_start[r + 1] as usize);
        self.kps[a..b].binary_search_by_key(&(c as u32), |k| k[1]).ok().map(|k| a + k)
    }

    fn saddle_at(&self, r: usize, c: usize) -> Option<&Saddle> {
        let k = self.kp_at(r, c)?;
        let s = self.saddle_of[k];
        (s != NONE).then(|| &self.saddles[s as usize])
    }

    /// Level of the terrace containing the lattice point (c, r), which must lie inside a
    /// terrace (not on a boundary): the pixel's level, or the joined level inside a chamfer.
    fn region(&self, c: f64, r: f64) -> u16 {
        let col = (c.floor().max(0.0) as usize).min(self.nc - 1);
        let row = (r.floor().max(0.0) as usize).min(self.nr - 1);
        let level = self.idx[row * self.nc + col];
        if self.saddles.is_empty() || r < (row + 1) as f64 - CHAMFER_FRACTION {
            return level;
        }
        // This pixel is TR of the corner at its bottom-left.
        match self.saddle_at(row + 1, col) {
            Some(s) if (c - col as f64) + ((row + 1) as f64 - r) < CHAMFER_FRACTION => s.joined(),
            _ => level,
        }
    }

    /// All boundary segments (including the outline and the chamfers).
    fn segments(&self) -> Vec<Segment> {
        let k_count = self.kps.len();
        let mut segs = Vec::with_capacity(k_count * 2);
        // Horizontal runs on each lattice row, walking +X: the pixel above is on the left.
        for r in 0..=self.nr {
            let (a, b) = (self.row_start[r] as usize, self.row_start[r + 1] as usize);
            for k in a..b.saturating_sub(1) {
                let c1 = self.kps[k][1] as isize;
                let above = self.px(r as isize - 1, c1);
                let below = self.px(r as isize, c1);
                if above == below {
                    continue;
                }
                // The run right of a saddle starts at its chamfer point B.
                let s = self.saddle_of[k];
                let p = if s != NONE { self.chamfer_b(s) } else { k as u32 };
                let q = (k + 1) as u32;
                segs.push(Segment { p, q, left: above, right: below });
            }
        }
        // Vertical runs on each lattice column, walking down the rows (-Y): the pixel on the
        // right (+X) is on the left of the walk.
        let mut col_start = vec![0u32; self.nc + 2];
        for k in &self.kps {
            col_start[k[1] as usize + 1] += 1;
        }
        for c in 0..=self.nc {
            col_start[c + 1] += col_start[c];
        }
        let mut fill = col_start.clone();
        let mut by_col = vec![0u32; k_count];
        for (k, kp) in self.kps.iter().enumerate() {
            let slot = &mut fill[kp[1] as usize];
            by_col[*slot as usize] = k as u32;
            *slot += 1;
        }
        for c in 0..=self.nc {
            let col = &by_col[col_start[c] as usize..col_start[c + 1] as usize];
            for w in col.windows(2) {
                let (k1, k2) = (w[0] as usize, w[1] as usize);
                let r1 = self.kps[k1][0] as isize;
                let lpx = self.px(r1, c as isize - 1);
                let rpx = self.px(r1, c as isize);
                if lpx == rpx {
                    continue;
                }
                // A saddle below cuts the lower end of the run above it.
                let s = self.saddle_of[k2];
                let q = if s != NONE { self.chamfer_a(s) } else { k2 as u32 };
                segs.push(Segment { p: k1 as u32, q, left: rpx, right: lpx });
            }
        }
        // Chamfers: A -> B runs (+d, -d) in (X, Y), the cut TR pixel on its left; and where TL
        // differs from BR, the short run from A down to the corner, BR's triangle on its left.
        for (s, sd) in self.saddles.iter().enumerate() {
            let (a, b) = (self.chamfer_a(s as u32), self.chamfer_b(s as u32));
            let [tl, tr, _, br] = sd.quad;
            segs.push(Segment { p: a, q: b, left: tr, right: br });
            if tl != br {
                segs.push(Segment { p: a, q: sd.kp, left: br, right: tl });
            }
        }
        segs
    }
}

/// One vertical chain of wall vertices at a point: (level key, vertex id), ascending.
struct Chain {
    items: [(i32, u32); 6],
    len: usize,
}

impl Chain {
    fn as_slice(&self) -> &[(i32, u32)] {
        &self.items[..self.len]
    }
}

/// The mesh under construction: vertex numbering per point.
struct Numbering<'a> {
    corners: &'a [Corner],
    first: Vec<u32>,
}

impl Numbering<'_> {
    fn top(&self, p: usize, level: u16) -> Result<u32> {
        let c = &self.corners[p];
        c.levels()
            .iter()
            .position(|&l| l == level)
            .map(|k| self.first[p] + k as u32)
            .ok_or_else(|| Error::internal(format!("terrace mesh: point {p} has no vertex at level {level}")))
    }
    fn base(&self, p: usize) -> Result<u32> {
        let c = &self.corners[p];
        if c.base {
            Ok(self.first[p] + c.n as u32)
        } else {
            Err(Error::internal(format!("terrace mesh: point {p} is not on the outline")))
        }
    }
    /// Vertices at point p from `lo` (a level or BASE) up to level `hi`, with every level of
    /// the point strictly in between.
    fn chain(&self, p: usize, lo: i32, hi: u16) -> Result<Chain> {
        let mut ch = Chain { items: [(0, 0); 6], len: 0 };
        let mut push = |item| {
            ch.items[ch.len] = item;
            ch.len += 1;
        };
        if lo == BASE {
            push((BASE, self.base(p)?));
        } else {
            push((lo, self.top(p, lo as u16)?));
        }
        for &l in self.corners[p].levels() {
            if (l as i32) > lo && l < hi {
                push((l as i32, self.top(p, l)?));
            }
        }
        push((hi as i32, self.top(p, hi)?));
        Ok(ch)
    }
}

/// Triangulates the wall between vertical chains `pc` (at P) and `qc` (at Q), both from the
/// bottom to the top, counter-clockwise seen from the side where P -> Q runs left to right.
fn zipper(pc: &[(i32, u32)], qc: &[(i32, u32)], tris: &mut Vec<[u32; 3]>) {
    let (mut i, mut k) = (0, 0);
    while i + 1 < pc.len() || k + 1 < qc.len() {
        if k + 1 < qc.len() && (i + 1 == pc.len() || qc[k + 1].0 <= pc[i + 1].0) {
            tris.push([pc[i].1, qc[k].1, qc[k + 1].1]);
            k += 1;
        } else {
            tris.push([pc[i].1, qc[k].1, pc[i + 1].1]);
            i += 1;
        }
    }
}

/// Builds the terrace mesh; inputs were checked by the caller.
pub(super) fn mesh(heights: &Grid, z_base: f64, base_thickness: f64) -> Result<Mesh> {
    let (nr, nc) = heights.dim();
    let (corners, limit) = ((nr as u64 + 1) * (nc as u64 + 1), u32::MAX as u64 / 4);
    if corners >= limit {
        let what = format!("a {nr} x {nc} map is too large for one STL mesh");
        return Err(Error::limit(Resource::Samples, corners as f64, (limit - 1) as f64, what));
    }
    let (idx, level_z) = level_indices(heights)?;
    let t = Terraces::trace(idx, nr, nc);
    let segs = t.segments();
    let n_points = t.corners.len();

    // Top: constrained Delaunay triangulation in the (X, Y) = (c, -r) plane.
    let verts: Vec<Point2<f64>> = (0..n_points)
        .map(|p| {
            let [c, r] = t.position(p);
            Point2::new(c, -r)
        })
        .collect();
    let edges: Vec<[usize; 2]> = segs.iter().map(|s| [s.p as usize, s.q as usize]).collect();
    let cdt = ConstrainedDelaunayTriangulation::<Point2<f64>>::bulk_load_cdt(verts, edges)
        .map_err(|e| Error::internal(format!("terrace mesh: triangulation failed: {e:?}")))?;
    if cdt.num_vertices() != n_points {
        return Err(Error::internal("terrace mesh: duplicate key points"));
    }

    let mut first = Vec::with_capacity(n_points + 1);
    let mut acc = 0u32;
    for c in &t.corners {
        first.push(acc);
        acc += c.vertex_count();
    }
    first.push(acc);
    let centre = acc;
    let num = Numbering { corners: &t.corners, first };

    let mut tris: Vec<[u32; 3]> = Vec::with_capacity(cdt.num_inner_faces() + 3 * segs.len());
    for face in cdt.inner_faces() {
        let ids = face.vertices().map(|v| v.fix().index());
        let pos = face.positions();
        let cx = (pos[0].x + pos[1].x + pos[2].x) / 3.0;
        let cy = (pos[0].y + pos[1].y + pos[2].y) / 3.0;
        let level = t.region(cx, -cy);
        tris.push([num.top(ids[0], level)?, num.top(ids[1], level)?, num.top(ids[2], level)?]);
    }
    drop(cdt);

    // Walls (lower side on the right of P -> Q) and the base fan under the outline.
    for s in &segs {
        let (lo, hi, low_on_left) = if s.left == OUT {
            (BASE, s.right, true)
        } else if s.right == OUT {
            (BASE, s.left, false)
        } else if s.left < s.right {
            (s.left as i32, s.right, true)
        } else {
            (s.right as i32, s.left, false)
        };
        let (p, q) = if low_on_left { (s.q as usize, s.p as usize) } else { (s.p as usize, s.q as usize) };
        let pc = num.chain(p, lo, hi)?;
        let qc = num.chain(q, lo, hi)?;
        zipper(pc.as_slice(), qc.as_slice(), &mut tris);
        if lo == BASE {
            tris.push([centre, num.base(q)?, num.base(p)?]);
        }
    }

    // Vertex positions, metres.
    let [ox, oy] = heights.origin();
    let [px, py] = heights.pitch();
    let frame = Frame { x0: ox - 0.5 * px, y0: oy - 0.5 * py, px, py };
    let mut vertices = Vec::with_capacity(centre as usize + 1);
    for (p, c) in t.corners.iter().enumerate() {
        let [col, row] = t.position(p);
        let [x, y] = frame.xy(col, row);
        for &l in c.levels() {
            vertices.push([x, y, level_z[l as usize]]);
        }
        if c.base {
            vertices.push([x, y, z_base]);
        }
    }
    let [x, y] = frame.xy(0.5 * nc as f64, 0.5 * nr as f64);
    vertices.push([x, y, z_base]);

    let chamfers = t.saddles.len() as u64;
    let lateral = if chamfers > 0 { CHAMFER_FRACTION * px * py / (px * px + py * py).sqrt() } else { 0.0 };
    Ok(Mesh {
        vertices,
        triangles: tris,
        kind: SurfaceKind::Terraces,
        naive_triangles: 2 * (nr as u64) * (nc as u64),
        max_height_error: 0.0,
        max_lateral_deviation: lateral,
        chamfers,
        base_thickness,
    })
}
