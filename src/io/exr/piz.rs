//! PIZ decompression of an OpenEXR chunk, channel sampling included (OpenEXR's
//! `PizCompressor::uncompress`, `ImfHuf.cpp` and `ImfWav.cpp`, BSD-3-Clause, Contributors to the
//! OpenEXR Project; the structure follows the `exr` crate's port, BSD-3-Clause).
//!
//! The chunk holds: a bitmap of the 16-bit words that occur (`minNonZero`, `maxNonZero`, the
//! bitmap bytes between them), then the Huffman-coded words (length `i32`, then `im`, `iM`,
//! table length, bit count `nBits`, a reserved word, the packed code lengths, the bits). The
//! decoded words are, channel after channel, each channel's `nx x ny` samples (a float sample
//! as two words), wavelet-transformed (a 2D Haar transform, 14-bit or 16-bit arithmetic) and
//! mapped through the bitmap's dense numbering.

use super::chunk::{num_samples, planar_to_lines, ChunkChannel};

type Res<T> = std::result::Result<T, String>;

const BITMAP_SIZE: usize = 8192;
const HUF_ENCSIZE: usize = (1 << 16) + 1;
const HUF_DECBITS: u32 = 14;
const SHORT_ZEROCODE_RUN: u64 = 59;
const LONG_ZEROCODE_RUN: u64 = 63;
const SHORTEST_LONG_RUN: u64 = 2 + LONG_ZEROCODE_RUN - SHORT_ZEROCODE_RUN;

/// Decompresses a PIZ chunk covering lines `first..=last` into the chunk's line layout.
pub(super) fn decompress(
    data: &[u8],
    chans: &[ChunkChannel],
    first: i32,
    last: i32,
    raw_size: usize,
) -> Res<Vec<u8>> {
    let mut pos = 0;
    let mut take = |n: usize| -> Res<&[u8]> {
        let s = data.get(pos..pos + n).ok_or("the data end inside the header")?;
        pos += n;
        Ok(s)
    };
    let min_nz = u16::from_le_bytes(take(2)?.try_into().expect("2 bytes")) as usize;
    let max_nz = u16::from_le_bytes(take(2)?.try_into().expect("2 bytes")) as usize;
    if max_nz >= BITMAP_SIZE {
        return Err(format!("bitmap end {max_nz} >= {BITMAP_SIZE}"));
    }
    let mut bitmap = vec![0u8; BITMAP_SIZE];
    if min_nz <= max_nz {
        bitmap[min_nz..=max_nz].copy_from_slice(take(max_nz - min_nz + 1)?);
    }
    // The reverse lookup: dense index -> word.
    let mut lut: Vec<u16> =
        (0..=u16::MAX).filter(|&i| i == 0 || bitmap[i as usize >> 3] & (1 << (i & 7)) != 0).collect();
    let max_value = (lut.len() - 1) as u16;
    lut.resize(1 << 16, 0);
    let length = i32::from_le_bytes(take(4)?.try_into().expect("4 bytes"));
    let length = usize::try_from(length).map_err(|_| format!("negative Huffman length {length}"))?;
    let coded = take(length)?;

    let words = raw_size / 2;
    let mut buf = huf_uncompress(coded, words)?;

    // Inverse wavelet transform, channel by channel (a float sample is two interleaved words).
    let mut start = 0;
    let mut planar = Vec::with_capacity(chans.len());
    for ch in chans {
        let (nx, ny, size) = (ch.nx, num_samples(ch.ys, first, last), ch.bytes / 2);
        let n = nx * ny * size;
        let part = buf.get_mut(start..start + n).ok_or("the words end before the last channel")?;
        for j in 0..size {
            wav2_decode(&mut part[j..], nx, size, ny, nx * size, max_value);
        }
        for w in part.iter_mut() {
            *w = lut[*w as usize];
        }
        planar.push(part.to_vec());
        start += n;
    }
    if start != words {
        return Err(format!("{words} words decoded, the channels hold {start}"));
    }
    Ok(planar_to_lines(&planar, chans, first, last))
}

/// OpenEXR's `hufUncompress`: exactly `n` words, or an error.
fn huf_uncompress(c: &[u8], n: usize) -> Res<Vec<u16>> {
    if c.len() < 20 {
        return Err("the Huffman header is cut".into());
    }
    let word = |k: usize| u32::from_le_bytes(c[4 * k..4 * k + 4].try_into().expect("4 bytes")) as usize;
    let (im, i_max, n_bits) = (word(0), word(1), word(3));
    if im >= HUF_ENCSIZE || i_max >= HUF_ENCSIZE {
        return Err(format!("Huffman table range {im}..{i_max} outside 0..{HUF_ENCSIZE}"));
    }
    let mut rest = &c[20..];
    let codes = unpack_enc_table(&mut rest, im, i_max)?;
    if n_bits > 8 * rest.len() {
        return Err(format!("{n_bits} Huffman bits in {} bytes", rest.len()));
    }
    let dec = build_dec_table(&codes, im, i_max)?;
    huf_decode(&codes, &dec, &rest[..n_bits.div_ceil(8)], n_bits, i_max, n)
}

/// Reads `n` bits (the stream is most-significant bit first).
fn get_bits(n: u32, c: &mut u64, lc: &mut u32, input: &mut &[u8]) -> Res<u64> {
    while *lc < n {
        let (&b, rest) = input.split_first().ok_or("the Huffman code table is cut")?;
        *c = (*c << 8) | b as u64;
        *lc += 8;
        *input = rest;
    }
    *lc -= n;
    Ok((*c >> *lc) & ((1 << n) - 1))
}

/// The code lengths (6 bits each, with runs of zero lengths), made canonical codes: each entry
/// holds `code << 6 | length` (OpenEXR's `hufUnpackEncTable` and `hufCanonicalCodeTable`).
fn unpack_enc_table(input: &mut &[u8], im: usize, i_max: usize) -> Res<Vec<u64>> {
    let mut codes = vec![0u64; HUF_ENCSIZE];
    let (mut c, mut lc) = (0u64, 0u32);
    let mut i = im;
    while i <= i_max {
        let l = get_bits(6, &mut c, &mut lc, input)?;
        codes[i] = l;
        let zeros = if l == LONG_ZEROCODE_RUN {
            (get_bits(8, &mut c, &mut lc, input)? + SHORTEST_LONG_RUN) as usize
        } else if l >= SHORT_ZEROCODE_RUN {
            (l - SHORT_ZEROCODE_RUN + 2) as usize
        } else {
            i += 1;
            continue;
        };
        if i + zeros > i_max + 1 {
            return Err("the Huffman code table runs past its end".into());
        }
        codes[i..i + zeros].fill(0);
        i += zeros;
    }
    // Canonical codes: for each length, the numerically first code (lengths 58 down to 1).
    let mut n = [0u64; 59];
    for &l in &codes {
        n[l as usize] += 1;
    }
    let mut code = 0u64;
    for l in (1..=58).rev() {
        let next = (code + n[l]) >> 1;
        n[l] = code;
        code = next;
    }
    for l in codes.iter_mut() {
        if *l > 0 {
            let len = *l as usize;
            *l |= n[len] << 6;
            n[len] += 1;
        }
    }
    Ok(codes)
}

/// A decoding-table entry: a short code (length, symbol) or the symbols of the long codes
/// sharing its first 14 bits.
#[derive(Clone)]
enum Dec {
    Empty,
    Short(u32, u32),
    Long(Vec<u32>),
}

fn build_dec_table(codes: &[u64], im: usize, i_max: usize) -> Res<Vec<Dec>> {
    let mut dec = vec![Dec::Empty; 1 << HUF_DECBITS];
    for (sym, &entry) in codes.iter().enumerate().take(i_max + 1).skip(im) {
        let (code, len) = (entry >> 6, (entry & 63) as u32);
        if len == 0 {
            continue;
        }
        if code >> len != 0 {
            return Err("invalid Huffman table entry".into());
        }
        if len > HUF_DECBITS {
            match &mut dec[(code >> (len - HUF_DECBITS)) as usize] {
                d @ Dec::Empty => *d = Dec::Long(vec![sym as u32]),
                Dec::Long(v) => v.push(sym as u32),
                Dec::Short(..) => return Err("invalid Huffman table entry".into()),
            }
        } else {
            let start = (code << (HUF_DECBITS - len)) as usize;
            for d in &mut dec[start..start + (1 << (HUF_DECBITS - len))] {
                if !matches!(d, Dec::Empty) {
                    return Err("invalid Huffman table entry".into());
                }
                *d = Dec::Short(len, sym as u32);
            }
        }
    }
    Ok(dec)
}

/// OpenEXR's `hufDecode`.
fn huf_decode(
    codes: &[u64],
    dec: &[Dec],
    mut input: &[u8],
    n_bits: usize,
    rlc: usize,
    n: usize,
) -> Res<Vec<u16>> {
    let mut out: Vec<u16> = Vec::with_capacity(n);
    let (mut c, mut lc) = (0u64, 0u32);
    // A symbol: a word, or the run-length symbol `rlc`, which repeats the last word by the
    // count in the next 8 bits.
    let emit = |sym: u32, c: &mut u64, lc: &mut u32, input: &mut &[u8], out: &mut Vec<u16>| -> Res<()> {
        if sym as usize == rlc {
            if *lc < 8 {
                let (&b, rest) = input.split_first().ok_or("a run length is cut")?;
                *c = (*c << 8) | b as u64;
                *lc += 8;
                *input = rest;
            }
            *lc -= 8;
            let count = (*c >> *lc) as u8 as usize;
            let last = *out.last().ok_or("a run before any word")?;
            if out.len() + count > n {
                return Err("more Huffman words than the chunk holds".into());
            }
            out.resize(out.len() + count, last);
        } else if out.len() < n {
            out.push(sym as u16);
        } else {
            return Err("more Huffman words than the chunk holds".into());
        }
        Ok(())
    };
    while let Some((&b, rest)) = input.split_first() {
        c = (c << 8) | b as u64;
        lc += 8;
        input = rest;
        while lc >= HUF_DECBITS {
            match &dec[((c >> (lc - HUF_DECBITS)) & ((1 << HUF_DECBITS) - 1)) as usize] {
                Dec::Short(len, sym) => {
                    lc -= len;
                    emit(*sym, &mut c, &mut lc, &mut input, &mut out)?;
                }
                Dec::Long(syms) => {
                    let mut found = None;
                    for &sym in syms {
                        let l = (codes[sym as usize] & 63) as u32;
                        while lc < l {
                            let Some((&b, rest)) = input.split_first() else { break };
                            c = (c << 8) | b as u64;
                            lc += 8;
                            input = rest;
                        }
                        if lc >= l && codes[sym as usize] >> 6 == (c >> (lc - l)) & ((1u64 << l) - 1) {
                            lc -= l;
                            found = Some(sym);
                            break;
                        }
                    }
                    let sym = found.ok_or("invalid Huffman code")?;
                    emit(sym, &mut c, &mut lc, &mut input, &mut out)?;
                }
                Dec::Empty => return Err("invalid Huffman code".into()),
            }
        }
    }
    // The last (short) codes, after dropping the padding bits of the last byte.
    let pad = ((8 - n_bits as i64).rem_euclid(8)) as u32;
    c >>= pad;
    lc = lc.checked_sub(pad).ok_or("Huffman bit count")?;
    while lc > 0 {
        match &dec[((c << (HUF_DECBITS - lc.min(HUF_DECBITS))) & ((1 << HUF_DECBITS) - 1)) as usize] {
            Dec::Short(len, sym) if *len <= lc => {
                lc -= len;
                emit(*sym, &mut c, &mut lc, &mut input, &mut out)?;
            }
            _ => return Err("invalid Huffman code at the end".into()),
        }
    }
    if out.len() != n {
        return Err(format!("{} Huffman words, expected {n}", out.len()));
    }
    Ok(out)
}

/// OpenEXR's `wdec14`: the inverse of the 14-bit Haar step.
fn wdec14(l: u16, h: u16) -> (u16, u16) {
    let (ls, hs) = (l as i16 as i32, h as i16 as i32);
    let ai = ls + (hs & 1) + (hs >> 1);
    (ai as i16 as u16, (ai - hs) as i16 as u16)
}

/// OpenEXR's `wdec16`: the inverse of the 16-bit (modulo) Haar step.
fn wdec16(l: u16, h: u16) -> (u16, u16) {
    const A_OFFSET: i32 = 1 << 15;
    const MOD_MASK: i32 = (1 << 16) - 1;
    let (m, d) = (l as i32, h as i32);
    let bb = (m - (d >> 1)) & MOD_MASK;
    let aa = (d + bb - A_OFFSET) & MOD_MASK;
    (aa as u16, bb as u16)
}

/// OpenEXR's `wav2Decode`: the inverse 2D wavelet transform of `nx x ny` words at strides
/// `ox` (x) and `oy` (y).
fn wav2_decode(buf: &mut [u16], nx: usize, ox: usize, ny: usize, oy: usize, max_value: u16) {
    let w14 = max_value < (1 << 14);
    let dec = |a: u16, b: u16| if w14 { wdec14(a, b) } else { wdec16(a, b) };
    let n = nx.min(ny);
    let mut p = 1usize;
    while p <= n {
        p <<= 1;
    }
    p >>= 1;
    let mut p2 = p;
    p >>= 1;
    while p >= 1 {
        let (ox1, oy1, ox2, oy2) = (ox * p, oy * p, ox * p2, oy * p2);
        let ey = oy * (ny - p2);
        let mut py = 0;
        while py <= ey {
            let mut px = py;
            let ex = py + ox * (nx - p2);
            while px <= ex {
                let (p01, p10) = (px + ox1, px + oy1);
                let p11 = p10 + ox1;
                let (i00, i10) = dec(buf[px], buf[p10]);
                let (i01, i11) = dec(buf[p01], buf[p11]);
                let (a, b) = dec(i00, i01);
                buf[px] = a;
                buf[p01] = b;
                let (a, b) = dec(i10, i11);
                buf[p10] = a;
                buf[p11] = b;
                px += ox2;
            }
            // An odd column left over.
            if nx & p != 0 {
                let p10 = px + oy1;
                let (a, b) = dec(buf[px], buf[p10]);
                buf[px] = a;
                buf[p10] = b;
            }
            py += oy2;
        }
        // An odd line left over.
        if ny & p != 0 {
            let mut px = py;
            let ex = py + ox * (nx - p2);
            while px <= ex {
                let p01 = px + ox1;
                let (a, b) = dec(buf[px], buf[p01]);
                buf[px] = a;
                buf[p01] = b;
                px += ox2;
            }
        }
        p2 = p;
        p >>= 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The 14- and 16-bit Haar steps invert OpenEXR's forward steps (`wenc14`, `wenc16`).
    #[test]
    fn haar_steps_invert_the_forward_transform() {
        let wenc14 = |a: u16, b: u16| {
            let (a, b) = (a as i16 as i32, b as i16 as i32);
            (((a + b) >> 1) as i16 as u16, (a - b) as i16 as u16)
        };
        let wenc16 = |a: u16, b: u16| {
            let ao = (a as i32 + (1 << 15)) & 0xffff;
            let mut m = (ao + b as i32) >> 1;
            let d = ao - b as i32;
            if d < 0 {
                m = (m + (1 << 15)) & 0xffff;
            }
            (m as u16, (d & 0xffff) as u16)
        };
        for (a, b) in [(0u16, 0u16), (1, 2), (16383, 0), (100, 16000), (5, 5)] {
            let (l, h) = wenc14(a, b);
            assert_eq!(wdec14(l, h), (a, b));
        }
        for (a, b) in [(0u16, 65535u16), (65535, 0), (40000, 123), (7, 60000)] {
            let (l, h) = wenc16(a, b);
            assert_eq!(wdec16(l, h), (a, b));
        }
    }
}
