//! What several integration tests share: the f64 reference solution of the discrete system, and
//! the domain cut to the source's component.

use harmonic_core::domain::Label;
use harmonic_core::map::Dims;
use harmonic_core::solve::{PSI_FRONTIER, PSI_SOURCE};

/// The exact discrete solution, independently of the core's solvers: the documented
/// discretisation (every interior ψ is the mean of its in-domain face neighbours, plus
/// `screening · ψ` for the screened system; source 0, frontier 1) solved by conjugate gradients
/// in f64 to a relative residual of 1e-13 — some seven orders below the f32 solvers.
pub fn exact_solution(dims: &Dims, labels: &[Label], screening: f64) -> Vec<f64> {
    let n = dims.len();
    let interior = |i: usize| labels[i] == Label::Interior;
    // A x = Σ_{in-domain j} (x_i − x_j), with x = 0 off the interior; b = Σ frontier neighbours.
    let apply = |x: &[f64], out: &mut [f64]| {
        for i in 0..n {
            let mut acc = 0.0;
            if interior(i) {
                acc += screening * x[i];
                dims.for_each_face_neighbour(dims.voxel(i), |j| {
                    if labels[j].in_domain() {
                        acc += x[i] - if interior(j) { x[j] } else { 0.0 };
                    }
                });
            }
            out[i] = acc;
        }
    };
    let dot = |a: &[f64], c: &[f64]| a.iter().zip(c).map(|(p, q)| p * q).sum::<f64>();
    let mut rhs = vec![0.0f64; n];
    for (i, r) in rhs.iter_mut().enumerate() {
        if interior(i) {
            dims.for_each_face_neighbour(dims.voxel(i), |j| {
                if labels[j] == Label::Frontier {
                    *r += f64::from(PSI_FRONTIER);
                }
            });
        }
    }
    let mut x = vec![0.0f64; n];
    let mut r = rhs.clone();
    let mut p = r.clone();
    let mut ap = vec![0.0f64; n];
    let target = 1e-13 * dot(&rhs, &rhs).sqrt();
    let mut rr = dot(&r, &r);
    for _ in 0..20 * n {
        if rr.sqrt() <= target {
            break;
        }
        apply(&p, &mut ap);
        let alpha = rr / dot(&p, &ap);
        for i in 0..n {
            x[i] += alpha * p[i];
            r[i] -= alpha * ap[i];
        }
        let rr_new = dot(&r, &r);
        for i in 0..n {
            p[i] = r[i] + rr_new / rr * p[i];
        }
        rr = rr_new;
    }
    (0..n)
        .map(|i| match labels[i] {
            Label::Interior => x[i],
            Label::Frontier => f64::from(PSI_FRONTIER),
            _ => f64::from(PSI_SOURCE),
        })
        .collect()
}

/// Keeps only the source's component, as the domain build does: what the source reaches through
/// non-frontier domain voxels stays, everything else becomes `Outside` (a room that furniture or
/// a missing door cuts off takes no part).
#[allow(
    dead_code,
    reason = "each test crate compiles its own copy of this module; properties.rs uses only the reference solution"
)]
pub fn keep_component(dims: &Dims, labels: &mut [Label], source: usize) {
    let mut reached = vec![false; dims.len()];
    let mut stack = vec![source];
    reached[source] = true;
    while let Some(i) = stack.pop() {
        if labels[i] == Label::Frontier {
            continue;
        }
        dims.for_each_face_neighbour(dims.voxel(i), |j| {
            if !reached[j] && labels[j] != Label::Outside {
                reached[j] = true;
                stack.push(j);
            }
        });
    }
    for (l, r) in labels.iter_mut().zip(&reached) {
        if !r {
            *l = Label::Outside;
        }
    }
}
