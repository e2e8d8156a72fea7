//! Tracing a binary raster into simple rectilinear polygons: the geometry of one mask layer.
//!
//! # Contract
//!
//! [`trace`] turns an `Array2<bool>` (row `r`, column `c`) into polygons that are
//!
//! * rectilinear, with vertices on pixel corners: vertex `[x, y]` is the top-left corner of
//!   pixel `(row = y, column = x)`, so pixel `(r, c)` is the unit square `[c, c+1] x [r, r+1]`;
//! * simple: one closed boundary that never touches itself (no repeated vertex, no hole);
//! * free of collinear or repeated consecutive vertices (edges alternate horizontal, vertical);
//! * non-overlapping, with a union exactly equal to the set of `true` pixels (pieces may share
//!   edges where a region was cut, and touch at single corners);
//! * consistently oriented: the shoelace area `sum x_i y_(i+1) - x_(i+1) y_i` is positive in
//!   the (x = column, y = row) frame, i.e. clockwise as the image is viewed (rows downward);
//! * at most `max_vertices` vertices each.
//!
//! # Algorithm
//!
//! 1. Each row is reduced to its runs of `true` pixels `[start, end)`.
//! 2. Runs are grouped into 4-connected components with a union-find over runs of adjacent
//!    rows that overlap by at least one pixel (diagonal contact does not connect).
//! 3. A piece (a 4-connected set of runs) is traced from its corners. On each horizontal grid
//!    line `y` the four pixels around every run end point are compared; a vertex with one or
//!    three covered pixels is a corner, a vertex with two diagonally opposite covered pixels
//!    (a "pinch") is two corners, one hugging each covered pixel, so that diagonal contact
//!    never joins the boundary. On every grid line the corners, sorted along the line, pair
//!    up consecutively into boundary edges (at a pinch the corner whose edge lies before the
//!    vertex is sorted first). Following the edges alternately horizontal and vertical gives
//!    the boundary loops; the first corner (top-left) lies on the outer loop.
//! 4. A piece whose boundary is one loop without pinches and with at most `max_vertices`
//!    corners is a simple polygon and is emitted. Any other piece is cut along a grid line
//!    across its longer side: through a hole or pinch (the one nearest the middle), or through
//!    the middle when it only has too many vertices. A cut through a hole's span opens that
//!    hole on both sides, a cut at a pinch separates its two pixels, and cutting never creates
//!    a hole (a pixel set lying in a half-plane can only enclose what the whole set enclosed).
//!    The cut parts are regrouped into 4-connected pieces and processed again.
//!    Every cut strictly shrinks the bounding box of each part along the cut axis, so the
//!    process ends (at worst with one-pixel-wide strips, which are rectangles). A work stack
//!    replaces recursion.
//!
//! Cost: every round over a piece is linear in its runs and corners; cutting near the middle
//! keeps the number of rounds per pixel logarithmic in the number of holes and pinches.

use ndarray::Array2;

use crate::error::{Error, Resource, Result};

/// A polygon as its vertices `[x, y]` = `[column, row]` in pixel-corner coordinates.
pub type Polygon = Vec<[u32; 2]>;

/// Most distinct vertices of a GDSII BOUNDARY (see [`crate::fabrication::gds`]).
pub const DEFAULT_MAX_VERTICES: usize = 8190;

/// A run of `true` pixels `[start, end)` in one row.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Run {
    row: u32,
    start: u32,
    end: u32,
}

/// Where a piece is cut: along the vertical grid line `x = c` (columns `< c` | `>= c`) or
/// the horizontal grid line `y = r` (rows `< r` | `>= r`).
#[derive(Debug, Clone, Copy)]
enum Cut {
    Column(u32),
    Row(u32),
}

enum Outcome {
    Simple(Polygon),
    Split(Cut),
}

/// Traces the `true` pixels of `mask` into simple, hole-free, non-overlapping rectilinear
/// polygons of at most `max_vertices` vertices each (see the module docs for the contract).
/// Polygons come out in a deterministic order. An all-`false` mask gives no polygon.
pub fn trace(mask: &Array2<bool>, max_vertices: usize) -> Result<Vec<Polygon>> {
    if max_vertices < 4 {
        return Err(Error::param(
            "max_vertices",
            format!("a polygon needs at least 4 vertices, got a limit of {max_vertices}"),
        ));
    }
    let (rows, cols) = mask.dim();
    if rows >= u32::MAX as usize || cols >= u32::MAX as usize {
        let side = rows.max(cols) as f64;
        let what = format!("a {rows} x {cols} raster is too large to trace");
        return Err(Error::limit(Resource::Samples, side, f64::from(u32::MAX - 1), what));
    }
    let runs = extract_runs(mask);
    let mut stack = components(&runs, None);
    stack.reverse();
    let mut tracer = Tracer::default();
    let mut out = Vec::new();
    while let Some(piece) = stack.pop() {
        match tracer.trace(&piece, max_vertices) {
            Outcome::Simple(p) => out.push(p),
            Outcome::Split(cut) => {
                let mut parts = match cut {
                    Cut::Column(c) => components(&split_runs(&piece, c), None),
                    Cut::Row(r) => components(&piece, Some(r)),
                };
                parts.reverse();
                stack.extend(parts);
            }
        }
    }
    Ok(out)
}

/// The runs of every row, sorted by (row, start); runs are maximal.
fn extract_runs(mask: &Array2<bool>) -> Vec<Run> {
    let mut runs = Vec::new();
    let mut buf = Vec::new();
    for (r, row) in mask.outer_iter().enumerate() {
        let line: &[bool] = match row.as_slice() {
            Some(s) => s,
            None => {
                buf.clear();
                buf.extend(row.iter().copied());
                &buf
            }
        };
        let mut c = 0;
        let n = line.len();
        while c < n {
            // Skip the background, then measure the run.
            match line[c..].iter().position(|&v| v) {
                None => break,
                Some(k) => c += k,
            }
            let start = c;
            c += line[c..].iter().position(|&v| !v).unwrap_or(n - c);
            runs.push(Run { row: r as u32, start: start as u32, end: c as u32 });
        }
    }
    runs
}

/// Splits runs at the vertical grid line `x = c`; the order (row, start) is kept.
fn split_runs(runs: &[Run], c: u32) -> Vec<Run> {
    let mut out = Vec::with_capacity(runs.len() + runs.len() / 8 + 1);
    for &r in runs {
        if r.start < c && c < r.end {
            out.push(Run { end: c, ..r });
            out.push(Run { start: c, ..r });
        } else {
            out.push(r);
        }
    }
    out
}

fn find(parent: &mut [u32], mut i: u32) -> u32 {
    while parent[i as usize] != i {
        let g = parent[parent[i as usize] as usize];
        parent[i as usize] = g;
        i = g;
    }
    i
}

/// Groups sorted runs into 4-connected components (runs of adjacent rows overlapping by at
/// least one pixel are connected; runs split at a cut column never overlap). With
/// `blocked_row = Some(r)`, rows `r - 1` and `r` are not connected. Components come out in
/// the order of their first run; each keeps the (row, start) order.
fn components(runs: &[Run], blocked_row: Option<u32>) -> Vec<Vec<Run>> {
    let n = runs.len();
    if n == 0 {
        return Vec::new();
    }
    let mut parent: Vec<u32> = (0..n as u32).collect();
    let mut prev = 0..0;
    let mut i = 0;
    while i < n {
        let row = runs[i].row;
        let mut k = i + 1;
        while k < n && runs[k].row == row {
            k += 1;
        }
        if !prev.is_empty() && runs[prev.start].row + 1 == row && blocked_row != Some(row) {
            let (mut a, mut b) = (prev.start, i);
            while a < prev.end && b < k {
                let (ra, rb) = (runs[a], runs[b]);
                if ra.start < rb.end && rb.start < ra.end {
                    let (x, y) = (find(&mut parent, a as u32), find(&mut parent, b as u32));
                    if x != y {
                        // The smaller index becomes the root: labels follow first runs.
                        let (lo, hi) = if x < y { (x, y) } else { (y, x) };
                        parent[hi as usize] = lo;
                    }
                }
                if ra.end <= rb.end {
                    a += 1;
                } else {
                    b += 1;
                }
            }
        }
        prev = i..k;
        i = k;
    }
    let mut label = vec![u32::MAX; n];
    let mut comp = vec![0u32; n];
    let mut count: Vec<usize> = Vec::new();
    for (i, c) in comp.iter_mut().enumerate() {
        let r = find(&mut parent, i as u32) as usize;
        if label[r] == u32::MAX {
            label[r] = count.len() as u32;
            count.push(0);
        }
        *c = label[r];
        count[label[r] as usize] += 1;
    }
    if count.len() == 1 {
        return vec![runs.to_vec()];
    }
    let mut out: Vec<Vec<Run>> = count.iter().map(|&c| Vec::with_capacity(c)).collect();
    for (run, &c) in runs.iter().zip(&comp) {
        out[c as usize].push(*run);
    }
    out
}

/// Reusable scratch space for tracing pieces.
#[derive(Default)]
struct Tracer {
    row_off: Vec<u32>,
    /// Corner positions, in the order found (grid line by grid line, then along x).
    pos: Vec<[u32; 2]>,
    /// Whether the corner's vertical edge lies above it (toward smaller y).
    up: Vec<bool>,
    /// Pinch vertices of the piece.
    pinches: Vec<[u32; 2]>,
    /// Corner indices sorted by (x, y).
    order: Vec<u32>,
    bucket: Vec<u32>,
    /// The corner at the other end of each corner's vertical edge.
    vpartner: Vec<u32>,
    visited: Vec<bool>,
}

impl Tracer {
    /// Traces one 4-connected piece (non-empty runs sorted by (row, start)).
    fn trace(&mut self, runs: &[Run], max_vertices: usize) -> Outcome {
        let ymin = runs[0].row;
        let ymax = runs[runs.len() - 1].row + 1;
        let (mut xmin, mut xmax) = (u32::MAX, 0);
        for r in runs {
            xmin = xmin.min(r.start);
            xmax = xmax.max(r.end);
        }
        // Offsets of each row's runs.
        let h = (ymax - ymin) as usize;
        self.row_off.clear();
        self.row_off.resize(h + 1, 0);
        for r in runs {
            self.row_off[(r.row - ymin) as usize + 1] += 1;
        }
        for k in 0..h {
            self.row_off[k + 1] += self.row_off[k];
        }
        // Corners, grid line by grid line.
        self.pos.clear();
        self.up.clear();
        self.pinches.clear();
        for y in ymin..=ymax {
            let k = (y - ymin) as usize;
            let above =
                if k > 0 { &runs[self.row_off[k - 1] as usize..self.row_off[k] as usize] } else { &[] };
            let below =
                if k < h { &runs[self.row_off[k] as usize..self.row_off[k + 1] as usize] } else { &[] };
            self.line(y, above, below);
        }
        let n = self.pos.len();
        // Sort corner indices by x (counting sort, stable: y stays increasing within a column).
        let w = (xmax - xmin) as usize + 1;
        self.bucket.clear();
        self.bucket.resize(w + 1, 0);
        for p in &self.pos {
            self.bucket[(p[0] - xmin) as usize + 1] += 1;
        }
        for k in 0..w {
            self.bucket[k + 1] += self.bucket[k];
        }
        self.order.clear();
        self.order.resize(n, 0);
        for (i, p) in self.pos.iter().enumerate() {
            let b = &mut self.bucket[(p[0] - xmin) as usize];
            self.order[*b as usize] = i as u32;
            *b += 1;
        }
        // At a pinch the corner whose vertical edge lies above comes first.
        for k in 1..n {
            let (a, b) = (self.order[k - 1] as usize, self.order[k] as usize);
            if self.pos[a] == self.pos[b] && !self.up[a] {
                self.order.swap(k - 1, k);
            }
        }
        // On each vertical grid line the sorted corners pair up consecutively. Every line holds
        // an even number of corners, so pairs never straddle two lines.
        self.vpartner.clear();
        self.vpartner.resize(n, 0);
        for pair in self.order.chunks_exact(2) {
            self.vpartner[pair[0] as usize] = pair[1];
            self.vpartner[pair[1] as usize] = pair[0];
        }
        // The outer loop starts at corner 0 (top-left) and leaves it along +x (the top edge):
        // corner i's horizontal partner is i ^ 1 because corners were found line by line.
        self.visited.clear();
        self.visited.resize(n, false);
        let outer = self.walk(0, |_| {});
        if outer == n && self.pinches.is_empty() && outer <= max_vertices {
            let mut poly = Vec::with_capacity(n);
            let mut cur = 0u32;
            loop {
                poly.push(self.pos[cur as usize]);
                poly.push(self.pos[(cur ^ 1) as usize]);
                cur = self.vpartner[(cur ^ 1) as usize];
                if cur == 0 {
                    break;
                }
            }
            return Outcome::Simple(poly);
        }
        // Defects: holes (the other loops) and pinches, as spans [lo, hi] along x and y of
        // the grid lines where a cut resolves them.
        let mut defects: Vec<[u32; 4]> = self.pinches.iter().map(|p| [p[0], p[0], p[1], p[1]]).collect();
        for s in 0..n {
            if !self.visited[s] {
                let mut b = [u32::MAX, 0, u32::MAX, 0];
                self.walk(s as u32, |p| {
                    b = [b[0].min(p[0]), b[1].max(p[0]), b[2].min(p[1]), b[3].max(p[1])];
                });
                defects.push(b);
            }
        }
        let by_columns = xmax - xmin >= ymax - ymin;
        let (lo, hi, axis) = if by_columns { (xmin, xmax, 0) } else { (ymin, ymax, 2) };
        // A cut at c splits the piece into two non-empty sides when lo < c < hi; the longer
        // side of a piece that is not a rectangle is at least 2 long.
        let mid = lo + (hi - lo) / 2;
        let mut cut = mid;
        let mut best = u32::MAX;
        for d in &defects {
            let c = mid.clamp(d[axis], d[axis + 1]).clamp(lo + 1, hi - 1);
            if c.abs_diff(mid) < best {
                best = c.abs_diff(mid);
                cut = c;
            }
        }
        Outcome::Split(if by_columns { Cut::Column(cut) } else { Cut::Row(cut) })
    }

    /// Follows the loop through corner `start` (horizontal edge first), marking its corners
    /// visited and calling `f` on each position; returns the number of corners.
    fn walk(&mut self, start: u32, mut f: impl FnMut([u32; 2])) -> usize {
        let mut len = 0;
        let mut cur = start;
        loop {
            for c in [cur, cur ^ 1] {
                self.visited[c as usize] = true;
                f(self.pos[c as usize]);
            }
            len += 2;
            cur = self.vpartner[(cur ^ 1) as usize];
            if cur == start {
                return len;
            }
        }
    }

    /// Finds the corners on the horizontal grid line `y`, between the row above (`above`)
    /// and the row below (`below`), in increasing x.
    fn line(&mut self, y: u32, above: &[Run], below: &[Run]) {
        let (mut i, mut j) = (0, 0);
        let (mut a, mut b) = (false, false);
        loop {
            let na = above.get(i).map(|r| if a { r.end } else { r.start });
            let nb = below.get(j).map(|r| if b { r.end } else { r.start });
            let x = match (na, nb) {
                (None, None) => break,
                (Some(p), None) => p,
                (None, Some(q)) => q,
                (Some(p), Some(q)) => p.min(q),
            };
            let (ul, dl) = (a, b);
            // Apply every toggle at x (touching runs toggle twice and cancel).
            while let Some(r) = above.get(i) {
                if (if a { r.end } else { r.start }) != x {
                    break;
                }
                a = !a;
                if !a {
                    i += 1;
                }
            }
            while let Some(r) = below.get(j) {
                if (if b { r.end } else { r.start }) != x {
                    break;
                }
                b = !b;
                if !b {
                    j += 1;
                }
            }
            let (ur, dr) = (a, b);
            match ul as u8 + ur as u8 + dl as u8 + dr as u8 {
                1 | 3 => {
                    self.pos.push([x, y]);
                    self.up.push(ul != ur);
                }
                2 if ul == dr => {
                    // Pinch: two corners, each hugging one covered pixel; the one whose
                    // horizontal edge lies left of x comes first.
                    self.pos.push([x, y]);
                    self.pos.push([x, y]);
                    if ul {
                        // Upper-left pixel (edges left and above), then lower-right pixel.
                        self.up.extend([true, false]);
                    } else {
                        // Lower-left pixel (edges left and below), then upper-right pixel.
                        self.up.extend([false, true]);
                    }
                    self.pinches.push([x, y]);
                }
                _ => {}
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Lcg;

    /// Even-odd scanline fill of each polygon, counting how many polygons cover each pixel.
    fn rasterize(polys: &[Polygon], rows: usize, cols: usize) -> Array2<u32> {
        let mut count = Array2::<u32>::zeros((rows, cols));
        for p in polys {
            for r in 0..rows {
                let yc = r as f64 + 0.5;
                let mut xs: Vec<u32> = Vec::new();
                for k in 0..p.len() {
                    let (a, b) = (p[k], p[(k + 1) % p.len()]);
                    if a[0] == b[0] && ((a[1] as f64) < yc) != ((b[1] as f64) < yc) {
                        xs.push(a[0]);
                    }
                }
                xs.sort_unstable();
                assert!(xs.len().is_multiple_of(2));
                for pair in xs.chunks(2) {
                    for c in pair[0]..pair[1] {
                        count[[r, c as usize]] += 1;
                    }
                }
            }
        }
        count
    }

    fn shoelace2(p: &Polygon) -> i64 {
        (0..p.len())
            .map(|k| {
                let (a, b) = (p[k], p[(k + 1) % p.len()]);
                a[0] as i64 * b[1] as i64 - b[0] as i64 * a[1] as i64
            })
            .sum()
    }

    /// Checks one polygon: rectilinear with alternating edges (no collinear or repeated
    /// vertex), a boundary that visits every lattice point at most once (simple, hence no
    /// hole), positive orientation, and the vertex limit.
    fn check_polygon(p: &Polygon, max_vertices: usize) {
        let n = p.len();
        assert!(n >= 4 && n.is_multiple_of(2) && n <= max_vertices, "{n} vertices");
        let mut seen = std::collections::HashSet::new();
        for k in 0..n {
            let (a, b, c) = (p[k], p[(k + 1) % n], p[(k + 2) % n]);
            let h1 = a[1] == b[1] && a[0] != b[0];
            let v1 = a[0] == b[0] && a[1] != b[1];
            let h2 = b[1] == c[1] && b[0] != c[0];
            assert!((h1 || v1) && (h1 != h2), "edges must alternate: {a:?} {b:?} {c:?}");
            // Walk the unit steps of edge a -> b, recording lattice points.
            let (dx, dy) = ((b[0] as i64 - a[0] as i64).signum(), (b[1] as i64 - a[1] as i64).signum());
            let (mut x, mut y) = (a[0] as i64, a[1] as i64);
            while (x, y) != (b[0] as i64, b[1] as i64) {
                assert!(seen.insert((x, y)), "boundary touches itself at {x}, {y}");
                x += dx;
                y += dy;
            }
        }
        assert!(shoelace2(p) > 0, "orientation");
    }

    fn check(mask: &Array2<bool>, max_vertices: usize) -> Vec<Polygon> {
        let polys = trace(mask, max_vertices).unwrap();
        for p in &polys {
            check_polygon(p, max_vertices);
        }
        let (rows, cols) = mask.dim();
        let count = rasterize(&polys, rows, cols);
        for ((i, j), &m) in mask.indexed_iter() {
            assert_eq!(count[[i, j]], m as u32, "pixel ({i}, {j})");
        }
        // Area check: the polygons' areas add up to the pixel count (no overlap, no gap).
        let area: i64 = polys.iter().map(|p| shoelace2(p) / 2).sum();
        assert_eq!(area, mask.iter().filter(|&&v| v).count() as i64);
        polys
    }

    #[test]
    fn random_masks_trace_back_exactly() {
        for seed in 0..40u64 {
            let mut g = Lcg(seed * 7919 + 1);
            let rows = 5 + (g.uniform() * 60.0) as usize;
            let cols = 5 + (g.uniform() * 60.0) as usize;
            let density = 0.2 + 0.6 * g.uniform();
            let mask = Array2::from_shape_fn((rows, cols), |_| g.uniform() < density);
            check(&mask, DEFAULT_MAX_VERTICES);
            // A tight vertex limit forces many cuts on the same shapes.
            check(&mask, 4 + 2 * (seed as usize % 7));
        }
    }

    #[test]
    fn blocky_masks_with_diagonal_contacts() {
        // Upsampled random blocks: the staircases and diagonal contacts of a resampled map.
        for seed in 0..10u64 {
            let mut g = Lcg(seed + 100);
            let coarse = Array2::from_shape_fn((12, 15), |_| g.uniform() < 0.5);
            let mask = Array2::from_shape_fn((12 * 4, 15 * 5), |(i, j)| coarse[[i / 4, j / 5]]);
            check(&mask, DEFAULT_MAX_VERTICES);
        }
    }

    #[test]
    fn checkerboard_gives_one_square_per_pixel() {
        let mask = Array2::from_shape_fn((9, 11), |(i, j)| (i + j) % 2 == 0);
        let polys = check(&mask, DEFAULT_MAX_VERTICES);
        assert_eq!(polys.len(), mask.iter().filter(|&&v| v).count());
        assert!(polys.iter().all(|p| p.len() == 4));
        // The complement too (its pixels touch the border differently).
        let inv = mask.mapv(|v| !v);
        let polys = check(&inv, DEFAULT_MAX_VERTICES);
        assert_eq!(polys.len(), inv.iter().filter(|&&v| v).count());
    }

    #[test]
    fn ring_with_holes_is_cut_into_simple_pieces() {
        // A square annulus, and a plate with three holes (one touching another diagonally).
        let ring = Array2::from_shape_fn((20, 20), |(i, j)| {
            let d = (i as i32 - 10).abs().max((j as i32 - 10).abs());
            (4..8).contains(&d)
        });
        let polys = check(&ring, DEFAULT_MAX_VERTICES);
        assert!(polys.len() >= 2, "an annulus cannot be one simple polygon");
        let mut plate = Array2::from_elem((16, 30), true);
        for (i, j) in [(3, 3), (3, 4), (4, 3), (8, 10), (9, 11), (12, 20), (12, 21), (13, 21)] {
            plate[[i, j]] = false;
        }
        let polys = check(&plate, DEFAULT_MAX_VERTICES);
        assert!(polys.len() >= 2);
        // A pinch of the region with itself: a 3 x 3 ring missing one corner.
        let mut pinch = Array2::from_elem((3, 3), true);
        pinch[[1, 1]] = false;
        pinch[[2, 2]] = false;
        check(&pinch, DEFAULT_MAX_VERTICES);
    }

    #[test]
    fn single_pixels_full_and_empty_images() {
        let mut one = Array2::from_elem((7, 5), false);
        one[[3, 2]] = true;
        let polys = check(&one, DEFAULT_MAX_VERTICES);
        assert_eq!(polys, vec![vec![[2, 3], [3, 3], [3, 4], [2, 4]]]);
        let corner = Array2::from_elem((1, 1), true);
        assert_eq!(check(&corner, 4), vec![vec![[0, 0], [1, 0], [1, 1], [0, 1]]]);
        let full = Array2::from_elem((13, 17), true);
        assert_eq!(check(&full, 4), vec![vec![[0, 0], [17, 0], [17, 13], [0, 13]]]);
        assert!(trace(&Array2::from_elem((4, 4), false), 8).unwrap().is_empty());
        assert!(trace(&full, 3).is_err());
    }

    #[test]
    fn vertex_limit_is_respected_on_a_comb() {
        // A comb of 600 teeth: 2 corners per tooth top and per gap bottom (599 inner gaps and
        // one open on the right), plus the 2 bottom corners: 2402 vertices.
        let mask = Array2::from_shape_fn((12, 1200), |(i, j)| i >= 10 || j % 2 == 0);
        let one = check(&mask, DEFAULT_MAX_VERTICES);
        assert_eq!(one.len(), 1);
        assert_eq!(one[0].len(), 2402);
        for limit in [4, 6, 50, 1000] {
            let polys = check(&mask, limit);
            assert!(polys.len() >= 2400 / limit);
        }
    }

    #[test]
    fn serpentine_above_the_gdsii_limit_is_split() {
        // A serpentine (one 4-connected path) with about 4 * 2500 = 10000 vertices.
        let (rows, cols) = (8, 5000);
        let mask = Array2::from_shape_fn((rows, cols), |(i, j)| {
            j % 2 == 0 || (i == 0 && j % 4 == 1) || (i == rows - 1 && j % 4 == 3)
        });
        let polys = check(&mask, DEFAULT_MAX_VERTICES);
        assert!(polys.len() >= 2);
        let total: usize = polys.iter().map(|p| p.len()).sum();
        assert!(total > DEFAULT_MAX_VERTICES);
    }

    #[test]
    fn non_standard_layout_is_read_correctly() {
        use ndarray::ShapeBuilder;
        let mut g = Lcg(5);
        let mask = Array2::from_shape_fn((30, 20), |_| g.uniform() < 0.5);
        // A column-major copy goes through the non-contiguous row path.
        let mut cm = Array2::from_elem((30, 20).f(), false);
        cm.assign(&mask);
        assert!(cm.row(0).as_slice().is_none());
        assert_eq!(trace(&cm, 100).unwrap(), check(&mask, 100));
    }
}
