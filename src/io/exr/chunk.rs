//! The layout of a chunk's samples that the decompressors share: how many samples a channel
//! has in a range of lines, what a decompressor knows of each channel, and the line layout
//! planar words are put back into.

/// Floor division (OpenEXR's `divp`) for a positive divisor.
fn divp(a: i64, s: i64) -> i64 {
    a.div_euclid(s)
}

/// How many multiples of `s` lie in `[a, b]` (OpenEXR's `numSamples`).
pub fn num_samples(s: i32, a: i32, b: i32) -> usize {
    let (s, a, b) = (s as i64, a as i64, b as i64);
    if b < a {
        return 0;
    }
    let (a1, b1) = (divp(a, s), divp(b, s));
    (b1 - a1 + if a1 * s < a { 0 } else { 1 }) as usize
}

/// What the decompressors need to know of a channel.
pub(crate) struct ChunkChannel {
    /// Bytes per sample.
    pub bytes: usize,
    /// Samples per line.
    pub nx: usize,
    /// y sampling.
    pub ys: i32,
    pub half: bool,
    /// B44 stores it on a log scale.
    pub linear: bool,
}

/// Lays per-channel planar `u16` words (the chunk's lines of one channel after another) out
/// as the chunk's line layout, little-endian.
pub(crate) fn planar_to_lines(planar: &[Vec<u16>], chans: &[ChunkChannel], first: i32, last: i32) -> Vec<u8> {
    let mut next = vec![0usize; chans.len()];
    let mut out = Vec::new();
    for y in first..=last {
        for (c, ch) in chans.iter().enumerate() {
            if y.rem_euclid(ch.ys) != 0 {
                continue;
            }
            let words = ch.nx * ch.bytes / 2;
            for &w in &planar[c][next[c]..next[c] + words] {
                out.extend_from_slice(&w.to_le_bytes());
            }
            next[c] += words;
        }
    }
    out
}
