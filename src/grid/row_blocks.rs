//! Parallel passes over the rows of 2-D arrays, in fixed blocks of [`ROW_BLOCK`] rows.
//!
//! Each block is handled by one thread in row-major order and the blocks' results come back in
//! row order, so a reduction that folds them in that order gives the same bits on any number of
//! threads (rayon's own `sum` or `reduce` would not: their grouping follows the work split).

use ndarray::{s, Array2, ArrayView2, ArrayViewMut2, Axis};
use rayon::prelude::*;

/// Rows per block.
pub const ROW_BLOCK: usize = 16;

/// `f(first_row, block)` for each block of up to [`ROW_BLOCK`] rows of `a`, in parallel; the
/// results in row order.
pub fn map_blocks<T, R, F>(a: &Array2<T>, f: F) -> Vec<R>
where
    T: Sync,
    R: Send,
    F: Fn(usize, ArrayView2<'_, T>) -> R + Sync + Send,
{
    let n = a.nrows();
    (0..n.div_ceil(ROW_BLOCK))
        .into_par_iter()
        .map(|b| {
            let r0 = b * ROW_BLOCK;
            f(r0, a.slice(s![r0..(r0 + ROW_BLOCK).min(n), ..]))
        })
        .collect()
}

/// `f(first_row, block)` for each block of up to [`ROW_BLOCK`] rows of `a`, mutable, in
/// parallel; the results in row order.
pub fn map_blocks_mut<T, R, F>(a: &mut Array2<T>, f: F) -> Vec<R>
where
    T: Send,
    R: Send,
    F: Fn(usize, ArrayViewMut2<'_, T>) -> R + Sync + Send,
{
    let blocks: Vec<ArrayViewMut2<'_, T>> = a.axis_chunks_iter_mut(Axis(0), ROW_BLOCK).collect();
    blocks.into_par_iter().enumerate().map(|(b, v)| f(b * ROW_BLOCK, v)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blocks_cover_every_row_once_in_order() {
        let mut a = Array2::from_shape_fn((3 * ROW_BLOCK + 5, 7), |(i, j)| (i * 7 + j) as f64);
        let firsts = map_blocks(&a, |r0, b| (r0, b.nrows(), b[[0, 0]]));
        assert_eq!(firsts.len(), 4);
        for (k, (r0, n, v)) in firsts.iter().enumerate() {
            assert_eq!(*r0, k * ROW_BLOCK);
            assert_eq!(*n, if k == 3 { 5 } else { ROW_BLOCK });
            assert_eq!(*v, (r0 * 7) as f64);
        }
        let rows = map_blocks_mut(&mut a, |r0, mut b| {
            b.mapv_inplace(|v| v + 1.0);
            r0
        });
        assert_eq!(rows, vec![0, ROW_BLOCK, 2 * ROW_BLOCK, 3 * ROW_BLOCK]);
        assert_eq!(a[[3 * ROW_BLOCK + 4, 6]], ((3 * ROW_BLOCK + 4) * 7 + 6 + 1) as f64);
    }
}
