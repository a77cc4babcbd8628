// Micro-benchmark (docs/experiments; not part of the build): red-black Gauss-Seidel sweeps of the
// screened operator on a 64 × 64 × 32 grid of rooms with one-voxel walls and doors, per-cell
// neighbour masks, in two layouts:
//   interleaved: both colours in one array, stride-2 sweeps, scalar, with the open-cell fast
//                path the core's fine sweep has (core/src/solve/multigrid.rs, relax_masked);
//   split:       red and black cells stored apart, each half sweep a contiguous loop over the
//                row's cells of one colour, masks applied as 0/1 weights (so it vectorises
//                on the SSE2 baseline; an if/else select vectorises only with wider targets).
// Both give the same values to the bit (printed as "max diff"). Best of 8 trials of 400 sweeps.
//
//   rustc -O -C debuginfo=0 docs/experiments/redblack-split-layout.rs -o /tmp/rb && /tmp/rb
//   rustc -O -C target-cpu=native docs/experiments/redblack-split-layout.rs -o /tmp/rbn && /tmp/rbn
use std::time::Instant;
const NX: usize = 64;
const NY: usize = 64;
const NZ: usize = 32;
const OPEN: u8 = 0x7f;
const INTERIOR: u8 = 0x40;

fn idx(x: usize, y: usize, z: usize) -> usize {
    x + NX * (y + NY * z)
}

fn world() -> Vec<bool> {
    // rooms with one-voxel walls every 16 voxels and doors; outer shell closed.
    let mut inside = vec![false; NX * NY * NZ];
    for z in 1..NZ - 1 {
        for y in 1..NY - 1 {
            for x in 1..NX - 1 {
                let wall_x = x % 16 == 0 && !(y % 16 > 6 && y % 16 < 10 && z < 20);
                let wall_y = y % 16 == 0 && !(x % 16 > 6 && x % 16 < 10 && z < 20);
                inside[idx(x, y, z)] = !(wall_x || wall_y);
            }
        }
    }
    inside
}

fn masks(inside: &[bool]) -> Vec<u8> {
    let mut m = vec![0u8; inside.len()];
    for z in 0..NZ {
        for y in 0..NY {
            for x in 0..NX {
                let i = idx(x, y, z);
                if !inside[i] {
                    continue;
                }
                let at = |ok: bool, j: usize| ok && inside[j];
                let f = [
                    at(x > 0, i.wrapping_sub(1)),
                    at(x + 1 < NX, i + 1),
                    at(y > 0, i.wrapping_sub(NX)),
                    at(y + 1 < NY, i + NX),
                    at(z > 0, i.wrapping_sub(NX * NY)),
                    at(z + 1 < NZ, i + NX * NY),
                ];
                let mut v = INTERIOR;
                for (k, b) in f.iter().enumerate() {
                    if *b {
                        v |= 1 << k;
                    }
                }
                m[i] = v;
            }
        }
    }
    m
}

fn sweep_interleaved(
    x: &mut [f32],
    b: &[f32],
    m: &[u8],
    shift: f32,
    inv: &[f32; 8],
    colour: usize,
) {
    for z in 1..NZ - 1 {
        for y in 1..NY - 1 {
            let s = idx(0, y, z);
            let first = (colour + y + z) & 1;
            let mut xx = if first == 0 { 2 } else { 1 };
            while xx < NX - 1 {
                let i = s + xx;
                let mk = m[i];
                if mk == OPEN {
                    let c = x[i];
                    let mut flux = 0.0f32;
                    flux += x[i - 1] - c;
                    flux += x[i + 1] - c;
                    flux += x[i - NX] - c;
                    flux += x[i + NX] - c;
                    flux += x[i - NX * NY] - c;
                    flux += x[i + NX * NY] - c;
                    x[i] = c + (flux - shift * c + b[i]) * inv[6];
                } else if mk & INTERIOR != 0 {
                    let c = x[i];
                    let mut flux = 0.0f32;
                    let nb = [
                        x[i - 1],
                        x[i + 1],
                        x[i - NX],
                        x[i + NX],
                        x[i - NX * NY],
                        x[i + NX * NY],
                    ];
                    for k in 0..6 {
                        flux += if mk & (1 << k) != 0 { nb[k] - c } else { 0.0 };
                    }
                    let n = (mk & 63).count_ones() as usize;
                    x[i] = c + (flux - shift * c + b[i]) * inv[n];
                }
                xx += 2;
            }
        }
    }
}

// Split: colour array `me` (red or black), other colour `ot`; each row has NX/2 cells.
// Cell k of row (y,z) of colour q is at x = 2k + p, p = (q + y + z) & 1.
fn sweep_split(me: &mut [f32], ot: &[f32], b: &[f32], m: &[u8], shift: f32, colour: usize) {
    const H: usize = NX / 2;
    for z in 1..NZ - 1 {
        for y in 1..NY - 1 {
            let r = H * (y + NY * z);
            let p = (colour + y + z) & 1;
            let row = &mut me[r..r + H];
            let br = &b[r..r + H];
            let mr = &m[r..r + H];
            let o = &ot[r..r + H];
            let ym = &ot[r - H..r];
            let yp = &ot[r + H..r + 2 * H];
            let zm = &ot[r - H * NY..r - H * NY + H];
            let zp = &ot[r + H * NY..r + H * NY + H];
            // x-neighbours: other colour at k - 1 + p and k + p, for k in (1 - p)..(H - p).
            let k0 = 1 - p;
            let len = H - 1;
            let lefts = &o[0..len];
            let rights = &o[1..1 + len];
            let it = row[k0..k0 + len]
                .iter_mut()
                .zip(&br[k0..k0 + len])
                .zip(&mr[k0..k0 + len])
                .zip(lefts.iter().zip(rights))
                .zip(ym[k0..k0 + len].iter().zip(&yp[k0..k0 + len]))
                .zip(zm[k0..k0 + len].iter().zip(&zp[k0..k0 + len]));
            for (((((cell, &bk), &mk), (&l, &rr)), (&a, &bb2)), (&cc, &dd)) in it {
                let c = *cell;
                let w = |d: u8, v: f32| ((mk >> d) & 1) as f32 * (v - c);
                let mut flux = 0.0f32;
                flux += w(0, l);
                flux += w(1, rr);
                flux += w(2, a);
                flux += w(3, bb2);
                flux += w(4, cc);
                flux += w(5, dd);
                let bit = |d: u8| ((mk >> d) & 1) as f32;
                let n = ((((bit(0) + bit(1)) + bit(2)) + bit(3)) + bit(4)) + bit(5);
                let new = c + (flux - shift * c + bk) / (n + shift);
                *cell = if mk & INTERIOR != 0 { new } else { c };
            }
        }
    }
}

fn main() {
    let inside = world();
    let m = masks(&inside);
    let n = NX * NY * NZ;
    let shift = 0.0918f32;
    let mut inv = [0.0f32; 8];
    for k in 0..7 {
        inv[k] = 1.0 / (k as f32 + shift);
    }
    let mut x = vec![0.0f32; n];
    let b: Vec<f32> = (0..n)
        .map(|i| {
            if inside[i] {
                ((i * 7919) % 1000) as f32 * 1e-3
            } else {
                0.0
            }
        })
        .collect();
    let sweeps = 400;
    let mut ti = f64::INFINITY;
    for _ in 0..8 {
        x.fill(0.0);
        let t = Instant::now();
        for _ in 0..sweeps {
            sweep_interleaved(&mut x, &b, &m, shift, &inv, 0);
            sweep_interleaved(&mut x, &b, &m, shift, &inv, 1);
        }
        ti = ti.min(t.elapsed().as_secs_f64());
    }
    let interior = inside.iter().filter(|&&v| v).count();
    // split copies
    let h = n / 2;
    let (mut red, mut black) = (vec![0.0f32; h], vec![0.0f32; h]);
    let (mut br, mut bb) = (vec![0.0f32; h], vec![0.0f32; h]);
    let (mut mred, mut mblack) = (vec![0u8; h], vec![0u8; h]);
    for z in 0..NZ {
        for y in 0..NY {
            for xx in 0..NX {
                let i = idx(xx, y, z);
                let j = (xx >> 1) + (NX / 2) * (y + NY * z);
                if (xx + y + z) & 1 == 0 {
                    br[j] = b[i];
                    mred[j] = m[i];
                } else {
                    bb[j] = b[i];
                    mblack[j] = m[i];
                }
            }
        }
    }
    let mut ts = f64::INFINITY;
    for _ in 0..8 {
        red.fill(0.0);
        black.fill(0.0);
        let t = Instant::now();
        for _ in 0..sweeps {
            sweep_split(&mut red, &black, &br, &mred, shift, 0);
            sweep_split(&mut black, &red, &bb, &mblack, shift, 1);
        }
        ts = ts.min(t.elapsed().as_secs_f64());
    }
    // compare results
    let mut maxd = 0.0f32;
    for z in 0..NZ {
        for y in 0..NY {
            for xx in 0..NX {
                let i = idx(xx, y, z);
                let j = (xx >> 1) + (NX / 2) * (y + NY * z);
                let v = if (xx + y + z) & 1 == 0 {
                    red[j]
                } else {
                    black[j]
                };
                maxd = maxd.max((v - x[i]).abs());
            }
        }
    }
    let upd = (sweeps * interior) as f64;
    println!("interior {interior}; interleaved {:.2} ns/update; split {:.2} ns/update; ratio {:.2}; max diff {maxd:e}",
        ti / upd * 1e9, ts / upd * 1e9, ti / ts);
}
