//! The binned, levelled images the coarse search correlates: the design and the scan averaged
//! onto a common coarse grid, each with its least-squares plane removed.

use rayon::prelude::*;

use crate::grid::Grid;

use super::refine::solve;

/// A real image centred on (0, 0) at `pitch`, row-major.
#[derive(Debug, Clone)]
pub(super) struct Img {
    pub(super) v: Vec<f64>,
    pub(super) rows: usize,
    pub(super) cols: usize,
    pub(super) pitch: [f64; 2],
}

impl Img {
    pub(super) fn centre(&self) -> (f64, f64) {
        ((self.rows as f64 - 1.0) * 0.5, (self.cols as f64 - 1.0) * 0.5)
    }

    /// Bilinear value at a position (metres from the centre), 0 outside.
    pub(super) fn bilinear(&self, x: [f64; 2]) -> f64 {
        let (ci, cj) = self.centre();
        let (fi, fj) = (x[1] / self.pitch[1] + ci, x[0] / self.pitch[0] + cj);
        if !(fi >= 0.0 && fj >= 0.0 && fi <= self.rows as f64 - 1.0 && fj <= self.cols as f64 - 1.0) {
            return 0.0;
        }
        let (i0, j0) = (fi.floor() as usize, fj.floor() as usize);
        let (i1, j1) = ((i0 + 1).min(self.rows - 1), (j0 + 1).min(self.cols - 1));
        let (ti, tj) = (fi - i0 as f64, fj - j0 as f64);
        let g = |i: usize, j: usize| self.v[i * self.cols + j];
        (1.0 - ti) * ((1.0 - tj) * g(i0, j0) + tj * g(i0, j1))
            + ti * ((1.0 - tj) * g(i1, j0) + tj * g(i1, j1))
    }
}

/// Bins a grid's valid samples into cells of `pitch` centred on the grid's centre (cell of a
/// sample = nearest cell centre). Returns the cell means (0 where empty) and counts.
pub(super) fn bin(g: &Grid, pitch: [f64; 2]) -> (Img, Vec<f64>) {
    let (nr, nc) = g.dim();
    let p = g.pitch();
    let cols = ((nc as f64 * p[0] / pitch[0]).ceil() as usize).max(1);
    let rows = ((nr as f64 * p[1] / pitch[1]).ceil() as usize).max(1);
    let mut sum = vec![0.0; rows * cols];
    let mut cnt = vec![0.0; rows * cols];
    let jmap: Vec<usize> = (0..nc)
        .map(|j| {
            let x = (j as f64 - (nc as f64 - 1.0) * 0.5) * p[0];
            ((x / pitch[0] + (cols as f64 - 1.0) * 0.5).round().max(0.0) as usize).min(cols - 1)
        })
        .collect();
    // Cell row of each sample row: non-decreasing, so each cell row takes a contiguous run of
    // sample rows. Cell rows are filled in parallel, each summing its samples in row-major
    // order (the same order, and so the same sums, on any number of threads).
    let imap: Vec<usize> = (0..nr)
        .map(|i| {
            let y = (i as f64 - (nr as f64 - 1.0) * 0.5) * p[1];
            ((y / pitch[1] + (rows as f64 - 1.0) * 0.5).round().max(0.0) as usize).min(rows - 1)
        })
        .collect();
    // Standard layout is contiguous, so the slices always exist.
    let values = g.values().as_standard_layout();
    let vals = values.as_slice().expect("standard layout is contiguous");
    let mask = g.mask().map(|m| m.as_standard_layout());
    let mvals = mask.as_ref().map(|m| m.as_slice().expect("standard layout is contiguous"));
    sum.par_chunks_mut(cols).zip(cnt.par_chunks_mut(cols)).enumerate().for_each(|(bi, (srow, crow))| {
        let (i0, i1) = (imap.partition_point(|&b| b < bi), imap.partition_point(|&b| b <= bi));
        for i in i0..i1 {
            let row = &vals[i * nc..(i + 1) * nc];
            let ok = mvals.map(|m| &m[i * nc..(i + 1) * nc]);
            for (j, &z) in row.iter().enumerate() {
                if ok.is_none_or(|m| m[j]) {
                    srow[jmap[j]] += z;
                    crow[jmap[j]] += 1.0;
                }
            }
        }
    });
    let v = sum.iter().zip(&cnt).map(|(s, c)| if *c > 0.0 { s / c } else { 0.0 }).collect();
    (Img { v, rows, cols, pitch }, cnt)
}

/// Removes the weighted least-squares plane from the occupied cells; empty cells become 0.
pub(super) fn level_img(img: &mut Img, w: &[f64]) {
    let (ci, cj) = img.centre();
    let mut a = [0.0; 9];
    let mut r = [0.0; 3];
    for i in 0..img.rows {
        for j in 0..img.cols {
            let k = i * img.cols + j;
            if w[k] > 0.0 {
                let f = [1.0, j as f64 - cj, i as f64 - ci];
                for p in 0..3 {
                    r[p] += w[k] * f[p] * img.v[k];
                    for q in 0..3 {
                        a[p * 3 + q] += w[k] * f[p] * f[q];
                    }
                }
            }
        }
    }
    let c = solve(&mut a, &mut r, 3).unwrap_or([0.0; 3].to_vec());
    for i in 0..img.rows {
        for j in 0..img.cols {
            let k = i * img.cols + j;
            img.v[k] = if w[k] > 0.0 {
                img.v[k] - c[0] - c[1] * (j as f64 - cj) - c[2] * (i as f64 - ci)
            } else {
                0.0
            };
        }
    }
}
