//! Error-bounded TIN of a continuous height map by greedy insertion (Garland & Heckbert 1995,
//! "Fast polygonal approximation of terrains and height fields", CMU-CS-95-181, algorithm III
//! with batched insertion).
//!
//! The surface interpolates pixel-centre samples linearly over a Delaunay triangulation whose
//! vertices are pixel centres. It starts from the four corner samples and the lowest and
//! highest samples (so the solid spans exactly the height range); each pass scans every
//! triangle that changed since the last pass, finds the pixel centre inside it farthest from
//! the triangle's plane (|h - interpolant|), and inserts that pixel for every triangle whose
//! worst error exceeds the tolerance. A pixel that is a vertex has error 0, so each pass adds
//! at least one new vertex and the loop ends, at the latest when every pixel is a vertex. When
//! no triangle exceeds the tolerance, a last scan of all triangles measures the exact maximum
//! over all pixel centres (every centre lies in some triangle).
//!
//! The outline runs through the outermost pixel centres: side walls stand on the perimeter
//! vertices, the base is a fan from its centre. Orientation as for terraces: `(X, Y) =
//! (j, -i)`, spade's counter-clockwise faces look up.

use ndarray::Array2;
use spade::handles::FixedVertexHandle;
use spade::{DelaunayTriangulation, Point2, Triangulation};

use super::mesh::{Frame, Mesh, SurfaceKind};
use crate::error::{Error, Resource, Result};
use crate::grid::Grid;

/// Largest |h - plane| over the pixel centres inside (or on) the triangle with pixel vertices
/// `v = [(i, j); 3]`, and the first pixel (row-major) that attains it.
fn worst_pixel(h: &Array2<f64>, v: [[u32; 2]; 3]) -> (f64, [u32; 2]) {
    let p = v.map(|[i, j]| (i as i64, j as i64, h[[i as usize, j as usize]]));
    let (i0, j0, z0) = p[0];
    let (di1, dj1, dz1) = (p[1].0 - i0, p[1].1 - j0, p[1].2 - z0);
    let (di2, dj2, dz2) = (p[2].0 - i0, p[2].1 - j0, p[2].2 - z0);
    // Plane z = z0 + a (j - j0) + b (i - i0) through the three samples (Cramer's rule).
    let det = (dj1 * di2 - dj2 * di1) as f64;
    let a = (dz1 * di2 as f64 - dz2 * di1 as f64) / det;
    let b = (dj1 as f64 * dz2 - dj2 as f64 * dz1) / det;
    let imin = p.iter().map(|q| q.0).min().unwrap_or(0);
    let imax = p.iter().map(|q| q.0).max().unwrap_or(0);
    let mut best = (-1.0, v[0]);
    for i in imin..=imax {
        // The triangle's extent along row i: where the row crosses the three edges. Integer
        // crossings are computed exactly (an exact quotient of integers), so pixels on an
        // edge are included by both triangles that share it.
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for (s, e) in [(0, 1), (1, 2), (2, 0)] {
            let ((ia, ja, _), (ib, jb, _)) = (p[s], p[e]);
            if ia == ib {
                if ia == i {
                    lo = lo.min(ja.min(jb) as f64);
                    hi = hi.max(ja.max(jb) as f64);
                }
            } else if (ia <= i && i <= ib) || (ib <= i && i <= ia) {
                let x = ja as f64 + ((i - ia) * (jb - ja)) as f64 / (ib - ia) as f64;
                lo = lo.min(x);
                hi = hi.max(x);
            }
        }
        if lo > hi {
            continue;
        }
        let row = h.row(i as usize);
        let base = z0 + b * (i - i0) as f64;
        for j in lo.ceil() as i64..=hi.floor() as i64 {
            let e = (row[j as usize] - (base + a * (j - j0) as f64)).abs();
            if e > best.0 {
                best = (e, [i as u32, j as u32]);
            }
        }
    }
    (best.0.max(0.0), best.1)
}

/// Builds the simplified heightfield mesh; inputs were checked by the caller.
pub(super) fn mesh(heights: &Grid, z_base: f64, base_thickness: f64, max_error: f64) -> Result<Mesh> {
    let (nr, nc) = heights.dim();
    let (samples, limit) = (nr as u64 * nc as u64, u32::MAX as u64 / 4);
    if samples >= limit {
        let what = format!("a {nr} x {nc} map is too large for one STL mesh");
        return Err(Error::limit(Resource::Samples, samples as f64, (limit - 1) as f64, what));
    }
    let h = heights.values();
    let fail =
        |e: spade::InsertionError| Error::internal(format!("heightfield mesh: insertion failed: {e:?}"));
    let mut tin: DelaunayTriangulation<Point2<f64>> = DelaunayTriangulation::new();
    let mut vpix: Vec<[u32; 2]> = Vec::new();
    // Inserts pixel (i, j), starting the point location at vertex `hint` when given.
    let insert = |tin: &mut DelaunayTriangulation<Point2<f64>>, vpix: &mut Vec<[u32; 2]>, i, j, hint| {
        let p = Point2::new(j as f64, -(i as f64));
        let v = match hint {
            Some(h) => tin.insert_with_hint(p, FixedVertexHandle::from_index(h)),
            None => tin.insert(p),
        }
        .map_err(fail)?;
        if v.index() != vpix.len() {
            return Err(Error::internal(format!("heightfield mesh: pixel ({i}, {j}) inserted twice")));
        }
        vpix.push([i, j]);
        Ok::<(), Error>(())
    };
    let (last_i, last_j) = (nr as u32 - 1, nc as u32 - 1);
    // Start from the corners and the (first) lowest and highest samples, so that the solid
    // spans exactly the height range plus the base.
    let mut start = vec![[0, 0], [0, last_j], [last_i, 0], [last_i, last_j]];
    let (mut lo, mut hi) = ([0u32, 0u32], [0u32, 0u32]);
    for ((i, j), &v) in h.indexed_iter() {
        if v < h[[lo[0] as usize, lo[1] as usize]] {
            lo = [i as u32, j as u32];
        }
        if v > h[[hi[0] as usize, hi[1] as usize]] {
            hi = [i as u32, j as u32];
        }
    }
    for p in [lo, hi] {
        if !start.contains(&p) {
            start.push(p);
        }
    }
    for [i, j] in start {
        insert(&mut tin, &mut vpix, i, j, None)?;
    }
    // Refinement. Every triangle an insertion creates has the new vertex as a corner, and every
    // triangle found bad is destroyed by the insertion of its worst pixel (inside it or on its
    // edge). So after a batch only the triangles touching a fresh vertex need scanning; the
    // others were scanned before and found good.
    let mut fresh: Vec<usize> = (0..vpix.len()).collect();
    let mut is_fresh = vec![true; vpix.len()];
    loop {
        // Worst pixels with a vertex of their triangle (a nearby start for point location).
        let mut worst: Vec<([u32; 2], usize)> = Vec::new();
        for &v in &fresh {
            for edge in tin.vertex(FixedVertexHandle::from_index(v)).out_edges() {
                let Some(face) = edge.face().as_inner() else { continue };
                let ids = face.vertices().map(|u| u.fix().index());
                // Scan each triangle once: from its smallest fresh vertex.
                if ids.iter().any(|&u| u < v && is_fresh[u]) {
                    continue;
                }
                let (e, px) = worst_pixel(h, ids.map(|k| vpix[k]));
                if e > max_error {
                    worst.push((px, v));
                }
            }
        }
        for &v in &fresh {
            is_fresh[v] = false;
        }
        fresh.clear();
        if worst.is_empty() {
            break;
        }
        // A pixel on a shared edge can be the worst of both triangles: insert it once.
        worst.sort_unstable();
        worst.dedup_by_key(|w| w.0);
        for ([i, j], hint) in worst {
            fresh.push(vpix.len());
            is_fresh.push(true);
            insert(&mut tin, &mut vpix, i, j, Some(hint))?;
        }
    }
    // The achieved error, measured over every pixel centre (each lies in some triangle).
    let max_height_error = tin
        .inner_faces()
        .map(|f| worst_pixel(h, f.vertices().map(|u| vpix[u.fix().index()])).0)
        .fold(0.0f64, f64::max);

    // Vertices: one top vertex per TIN vertex (same index), then a base vertex per outline
    // vertex, then the base centre.
    let [px, py] = heights.pitch();
    let frame = Frame { x0: heights.origin()[0], y0: heights.origin()[1], px, py };
    let mut vertices: Vec<[f64; 3]> = vpix
        .iter()
        .map(|&[i, j]| {
            let [x, y] = frame.xy(j as f64, i as f64);
            [x, y, h[[i as usize, j as usize]]]
        })
        .collect();
    let mut tris: Vec<[u32; 3]> =
        tin.inner_faces().map(|f| f.vertices().map(|v| v.fix().index() as u32)).collect();
    drop(tin);

    // Outline vertices counter-clockwise in (X, Y): along the last row (j up), the last column
    // (i down), the first row (j down), the first column (i up).
    let (li, lj) = (last_i as u64, last_j as u64);
    let key = |[i, j]: [u32; 2]| -> Option<u64> {
        let (i, j) = (i as u64, j as u64);
        if i == li {
            Some(j)
        } else if j == lj {
            Some(lj + (li - i))
        } else if i == 0 {
            Some(lj + li + (lj - j))
        } else if j == 0 {
            Some(2 * lj + li + i)
        } else {
            None
        }
    };
    let mut outline: Vec<(u64, u32)> =
        vpix.iter().enumerate().filter_map(|(v, &p)| key(p).map(|k| (k, v as u32))).collect();
    outline.sort_unstable();
    let mut base_of = Vec::with_capacity(outline.len());
    for &(_, v) in &outline {
        let [x, y, _] = vertices[v as usize];
        base_of.push(vertices.len() as u32);
        vertices.push([x, y, z_base]);
    }
    let centre = vertices.len() as u32;
    let [x, y] = frame.xy(0.5 * lj as f64, 0.5 * li as f64);
    vertices.push([x, y, z_base]);
    for k in 0..outline.len() {
        let n = (k + 1) % outline.len();
        let (pt, qt) = (outline[k].1, outline[n].1);
        let (pb, qb) = (base_of[k], base_of[n]);
        tris.push([pb, qb, qt]);
        tris.push([pb, qt, pt]);
        tris.push([centre, qb, pb]);
    }
    Ok(Mesh {
        vertices,
        triangles: tris,
        kind: SurfaceKind::Heightfield,
        naive_triangles: 2 * li * lj,
        max_height_error,
        max_lateral_deviation: 0.5 * px.max(py),
        chamfers: 0,
        base_thickness,
    })
}
