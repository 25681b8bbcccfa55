//! The projection's trial point over one vertex task (fepr-spec section 3: `q - alpha D^-1 G lambda` with a
//! diagonal position metric), written row by row, and the sums that need only the new rows, taken from them
//! while they are in registers: the constraints' sums (as [`crate::projection::constraint_lanes`] takes
//! them) and the D-norm distance from q~ (as [`correction_lanes`] takes it). The sums run in lanes of [`VL`]
//! rows, each lane in row order, and the caller adds the lanes in lane order: the same bits for any thread
//! count.
//!
//! Two implementations of the same operations: a portable one, and an explicit AVX2 kernel picked at run
//! time. Every row and every lane runs the same multiplications, additions and subtractions in the same order
//! (no fused multiply-adds), so both give the same bits (gated by
//! `avx2_trial_matches_the_portable_rows_and_sums_bit_for_bit`). Why a kernel: the portable row loop compiles
//! to scalar arithmetic on three-component rows, and the pass that writes a symplectic Euler step's trial
//! point took 12 ns per vertex on one thread (elephant, perf: the rows 7, the D-norm 3.5, the constraint sums
//! 1.5), as much as the projection's 45 moments for `S`. With the kernel: 7.4 ns (85 -> 52 us per pass on the
//! elephant's 7,008 vertices, temporary timers), about 56 vector operations per row.
//!
//! Padding: the last group of a task with fewer than [`VL`] rows gets lanes of unit mass, zero state and zero
//! gradient, pinned and with a zero metric factor, so every sum gets `+0` or `-0` from them and no row is
//! written for them.

use crate::math::{cross, dot, sub, Vec3};
use crate::projection::{Lane, CONSTRAINT_SUMS, VL};

/// The multipliers and constants of one trial step.
#[derive(Clone, Copy, Debug)]
pub(crate) struct StepCoefficients {
    /// The energy row's multiplier `lambda_H`.
    pub lh: f64,
    /// The step length `alpha`.
    pub alpha: f64,
    /// `1 / h^2` (1/s^2).
    pub inv_h2: f64,
    /// The momentum rows' multipliers `lambda_P`.
    pub lp: Vec3,
    /// The angular momentum rows' multipliers `lambda_L`.
    pub ll: Vec3,
    /// The centre of mass rows' multipliers over the total mass, `lambda_C / m_total`.
    pub lc_over_mt: Vec3,
    /// Gravitational acceleration (m/s^2).
    pub gravity: Vec3,
    /// The target centre of mass (m), about which the angular momentum is taken.
    pub center: Vec3,
}

/// One task's rows of the current iterate and of the metric (all the same length).
#[derive(Clone, Copy)]
pub(crate) struct IterateRows<'a> {
    /// Positions (m).
    pub x: &'a [Vec3],
    /// Velocities (m/s).
    pub v: &'a [Vec3],
    /// The elastic gradient at `x` (J/m).
    pub grad: &'a [Vec3],
    /// Masses (kg).
    pub mass: &'a [f64],
    /// The metric factor `a_i = m_i / w_i` (0: the position is frozen).
    pub factor: &'a [f64],
    /// `a_i / m_i`.
    pub a_over_m: &'a [f64],
    /// Pinned vertices keep their rows.
    pub pinned: &'a [bool],
    /// No row is pinned and every factor is 1 (the mass metric on a free body without frozen positions): the
    /// kernel then neither multiplies by the factors, nor divides by them, nor keeps pinned rows (the same bits).
    pub unit: bool,
}

/// The rows of the state that the D-norm distance is measured from (q~), and `h^2` (s^2).
#[derive(Clone, Copy)]
pub(crate) struct BaseRows<'a> {
    pub x: &'a [Vec3],
    pub v: &'a [Vec3],
    pub h2: f64,
}

/// The lane sums of one trial task: the constraints' (if asked for) and the D-norm distance's (if a base was
/// given).
#[derive(Clone, Copy, Debug)]
pub(crate) struct TrialSums {
    pub constraints: Option<[Lane; CONSTRAINT_SUMS]>,
    pub correction: Option<Lane>,
}

/// Writes the trial rows of `rows` into `x_out`, `v_out` (a pinned row keeps its own) and returns their sums:
/// the constraints' if `constraints`, the D-norm distance from `base` if given.
pub(crate) fn write_trial(
    step: &StepCoefficients,
    rows: &IterateRows,
    base: Option<BaseRows>,
    constraints: bool,
    x_out: &mut [Vec3],
    v_out: &mut [Vec3],
) -> TrialSums {
    let n = rows.x.len();
    assert!(
        [
            rows.v.len(),
            rows.grad.len(),
            rows.mass.len(),
            rows.factor.len(),
            rows.a_over_m.len(),
            rows.pinned.len(),
            x_out.len(),
            v_out.len(),
            base.map_or(n, |b| b.x.len()),
            base.map_or(n, |b| b.v.len()),
        ]
        .iter()
        .all(|&k| k == n),
        "one row per vertex"
    );
    debug_assert!(
        !rows.unit || (!rows.pinned.contains(&true) && rows.factor.iter().all(|&a| a == 1.0)),
        "unit rows are free with a unit factor"
    );
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked above); the lengths agree (asserted above).
        return unsafe { avx2::write_trial(step, rows, base, constraints, x_out, v_out) };
    }
    portable::write_trial(step, rows, base, constraints, x_out, v_out)
}

/// The lanes of the D-norm distance `sum m_i (|x_i - xb_i|^2 / a_i + h^2 |v_i - vb_i|^2)` of the rows `x`,
/// `v` from `base` (a frozen position, `a_i = 0`, adds no position term), as [`write_trial`] sums it.
pub(crate) fn correction_lanes(
    x: &[Vec3],
    v: &[Vec3],
    base: BaseRows,
    mass: &[f64],
    factor: &[f64],
) -> Lane {
    let n = x.len();
    assert!(
        [
            v.len(),
            base.x.len(),
            base.v.len(),
            mass.len(),
            factor.len()
        ]
        .iter()
        .all(|&k| k == n),
        "one row per vertex"
    );
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: as in write_trial.
        return unsafe { avx2::correction_lanes(x, v, base, mass, factor) };
    }
    portable::correction_lanes(x, v, base, mass, factor)
}

/// One row of the trial point: `x - alpha dx`, `v - alpha dv`, with `dx = W^-1` (the x-block of `G lambda`)
/// and `dv` the v-block over `m h^-2` (no division: `a_over_m` is kept with the metric).
#[inline(always)]
fn trial_row(
    c: &StepCoefficients,
    (x, v, gr): (Vec3, Vec3, Vec3),
    m: f64,
    a: f64,
    a_over_m: f64,
) -> (Vec3, Vec3) {
    let vxl = cross(v, c.ll);
    let lxr = cross(c.ll, sub(x, c.center));
    let (mut xo, mut vo) = ([0.0; 3], [0.0; 3]);
    for k in 0..3 {
        let gi = gr[k] - m * c.gravity[k];
        let dx = c.lh * gi * a_over_m + a * (vxl[k] + c.lc_over_mt[k]);
        xo[k] = x[k] - c.alpha * dx;
        let dv = (c.lh * v[k] + c.lp[k] + lxr[k]) * c.inv_h2;
        vo[k] = v[k] - c.alpha * dv;
    }
    (xo, vo)
}

/// The reference implementation, for any CPU.
pub(crate) mod portable {
    use super::*;

    /// One row's term of the D-norm distance.
    #[inline(always)]
    fn correction_term(x: Vec3, v: Vec3, xb: Vec3, vb: Vec3, m: f64, a: f64, h2: f64) -> f64 {
        let (dx, dv) = (sub(x, xb), sub(v, vb));
        let dx2 = if a > 0.0 { dot(dx, dx) / a } else { 0.0 };
        m * (dx2 + h2 * dot(dv, dv))
    }

    pub(crate) fn correction_lanes(
        x: &[Vec3],
        v: &[Vec3],
        base: BaseRows,
        mass: &[f64],
        factor: &[f64],
    ) -> Lane {
        let mut acc = [0.0; VL];
        for start in (0..x.len()).step_by(VL) {
            for (l, lane) in acc.iter_mut().enumerate() {
                let k = start + l;
                *lane += if k < x.len() {
                    correction_term(
                        x[k], v[k], base.x[k], base.v[k], mass[k], factor[k], base.h2,
                    )
                } else {
                    // A padding lane: unit mass, zero state, zero factor.
                    correction_term([0.0; 3], [0.0; 3], [0.0; 3], [0.0; 3], 1.0, 0.0, base.h2)
                };
            }
        }
        acc
    }

    pub(crate) fn write_trial(
        step: &StepCoefficients,
        rows: &IterateRows,
        base: Option<BaseRows>,
        constraints: bool,
        x_out: &mut [Vec3],
        v_out: &mut [Vec3],
    ) -> TrialSums {
        for (k, (xo, vo)) in x_out.iter_mut().zip(v_out.iter_mut()).enumerate() {
            (*xo, *vo) = if rows.pinned[k] {
                (rows.x[k], rows.v[k])
            } else {
                let state = (rows.x[k], rows.v[k], rows.grad[k]);
                trial_row(step, state, rows.mass[k], rows.factor[k], rows.a_over_m[k])
            };
        }
        let (x, v) = (&*x_out, &*v_out);
        TrialSums {
            constraints: constraints.then(|| {
                crate::projection::moments::portable::constraint_lanes(
                    x,
                    v,
                    rows.mass,
                    step.gravity,
                    step.center,
                )
            }),
            correction: base.map(|b| correction_lanes(x, v, b, rows.mass, rows.factor)),
        }
    }
}

/// The same rows and sums in an explicit AVX2 kernel: every row and lane runs the portable version's
/// operations in its order.
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::*;
    use crate::projection::avx2::{
        add, constraint_group, cross_at, load_rows, mul, norm2, splat3, store, sub,
    };
    use std::arch::x86_64::*;

    /// Three lane vectors (x, y, z of four rows) as four rows of three `f64` (12 consecutive values at `p`):
    /// the inverse of [`load_rows`].
    #[inline]
    #[target_feature(enable = "avx2")]
    unsafe fn store_rows(p: *mut f64, [x, y, z]: [__m256d; 3]) {
        let xy = _mm256_unpacklo_pd(x, y); // x0 y0 x2 y2
        let zx = _mm256_shuffle_pd::<0b1010>(z, x); // z0 x1 z2 x3
        let yz = _mm256_shuffle_pd::<0b1111>(y, z); // y1 z1 y3 z3
        let a = _mm256_permute2f128_pd::<0x20>(xy, zx); // x0 y0 z0 x1
        let b = _mm256_blend_pd::<0b1100>(yz, xy); // y1 z1 x2 y2
        let c = _mm256_permute2f128_pd::<0x31>(zx, yz); // z2 x3 y3 z3
                                                        // SAFETY (caller): p..p + 12 is writable.
        unsafe {
            _mm256_storeu_pd(p, a);
            _mm256_storeu_pd(p.add(4), b);
            _mm256_storeu_pd(p.add(8), c);
        }
    }

    /// One group's input rows in lanes.
    #[derive(Clone, Copy)]
    struct Group {
        x: [__m256d; 3],
        v: [__m256d; 3],
        grad: [__m256d; 3],
        m: __m256d,
        a: __m256d,
        a_over_m: __m256d,
        /// All bits set on a free row's lane, clear on a pinned row's or a padding lane.
        free: __m256d,
    }

    /// The lanes of four `pinned` flags: all bits set where the flag is false.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn free_mask(pinned: [bool; VL]) -> __m256d {
        let flags = _mm256_setr_epi64x(
            i64::from(pinned[0]),
            i64::from(pinned[1]),
            i64::from(pinned[2]),
            i64::from(pinned[3]),
        );
        _mm256_castsi256_pd(_mm256_cmpeq_epi64(flags, _mm256_setzero_si256()))
    }

    /// The group of rows `start .. start + VL` (all present); with `UNIT`, every lane free.
    #[inline]
    #[target_feature(enable = "avx2")]
    unsafe fn group<const UNIT: bool>(rows: &IterateRows, start: usize) -> Group {
        let p = if UNIT {
            &[false; VL][..]
        } else {
            &rows.pinned[start..start + VL]
        };
        // SAFETY (caller): start + VL <= n rows of every slice (asserted by write_trial).
        unsafe {
            Group {
                x: load_rows(rows.x.as_ptr().add(start).cast()),
                v: load_rows(rows.v.as_ptr().add(start).cast()),
                grad: load_rows(rows.grad.as_ptr().add(start).cast()),
                m: _mm256_loadu_pd(rows.mass.as_ptr().add(start)),
                a: _mm256_loadu_pd(rows.factor.as_ptr().add(start)),
                a_over_m: _mm256_loadu_pd(rows.a_over_m.as_ptr().add(start)),
                free: free_mask([p[0], p[1], p[2], p[3]]),
            }
        }
    }

    /// The constants of a step in lanes.
    struct Splat {
        lh: __m256d,
        alpha: __m256d,
        inv_h2: __m256d,
        lp: [__m256d; 3],
        ll: [__m256d; 3],
        lc: [__m256d; 3],
        g: [__m256d; 3],
        center: [__m256d; 3],
        h2: __m256d,
    }

    /// The trial rows of a group (a pinned row's lanes keep their rows): [`trial_row`] lane by lane. `UNIT`
    /// (every lane free with `a = 1`): the same bits without the factor's products (`1 x = x`) and the blends.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn trial_group<const UNIT: bool>(c: &Splat, gr: &Group) -> ([__m256d; 3], [__m256d; 3]) {
        let r: [__m256d; 3] = std::array::from_fn(|k| sub(gr.x[k], c.center[k]));
        let (mut xo, mut vo) = ([_mm256_setzero_pd(); 3], [_mm256_setzero_pd(); 3]);
        for k in 0..3 {
            let vxl = cross_at(&gr.v, &c.ll, k);
            let lxr = cross_at(&c.ll, &r, k);
            let gi = sub(gr.grad[k], mul(gr.m, c.g[k]));
            let rigid = add(vxl, c.lc[k]);
            let rigid = if UNIT { rigid } else { mul(gr.a, rigid) };
            let dx = add(mul(mul(c.lh, gi), gr.a_over_m), rigid);
            let dv = mul(add(add(mul(c.lh, gr.v[k]), c.lp[k]), lxr), c.inv_h2);
            let (x_new, v_new) = (
                sub(gr.x[k], mul(c.alpha, dx)),
                sub(gr.v[k], mul(c.alpha, dv)),
            );
            if UNIT {
                (xo[k], vo[k]) = (x_new, v_new);
                continue;
            }
            // blendv takes the second operand where the mask's sign bit is set: the new row on a free lane.
            xo[k] = _mm256_blendv_pd(gr.x[k], x_new, gr.free);
            vo[k] = _mm256_blendv_pd(gr.v[k], v_new, gr.free);
        }
        (xo, vo)
    }

    /// A group's terms of the D-norm distance from `(xb, vb)`: the portable `correction_term` lane by lane.
    /// `UNIT` (`a = 1` on every lane): the same bits without the division (`y / 1 = y`).
    #[inline]
    #[target_feature(enable = "avx2")]
    fn correction_group<const UNIT: bool>(
        x: &[__m256d; 3],
        v: &[__m256d; 3],
        xb: &[__m256d; 3],
        vb: &[__m256d; 3],
        m: __m256d,
        a: __m256d,
        h2: __m256d,
    ) -> __m256d {
        let dx: [__m256d; 3] = std::array::from_fn(|k| sub(x[k], xb[k]));
        let dv: [__m256d; 3] = std::array::from_fn(|k| sub(v[k], vb[k]));
        // dx^2 / a where a > 0, else 0 (the and clears the lanes of a frozen position, 0/0 included).
        let dx2 = if UNIT {
            norm2(&dx)
        } else {
            let positive = _mm256_cmp_pd::<_CMP_GT_OQ>(a, _mm256_setzero_pd());
            _mm256_and_pd(_mm256_div_pd(norm2(&dx), a), positive)
        };
        mul(m, add(dx2, mul(h2, norm2(&dv))))
    }

    /// The last `n - start` (< VL) rows, padded (see the module's note).
    struct Padded {
        x: [f64; 12],
        v: [f64; 12],
        grad: [f64; 12],
        xb: [f64; 12],
        vb: [f64; 12],
        m: [f64; VL],
        a: [f64; VL],
        a_over_m: [f64; VL],
        pinned: [bool; VL],
    }

    impl Padded {
        #[cold]
        #[inline(never)]
        fn new(rows: &IterateRows, base: Option<BaseRows>, start: usize) -> Self {
            let mut p = Padded {
                x: [0.0; 12],
                v: [0.0; 12],
                grad: [0.0; 12],
                xb: [0.0; 12],
                vb: [0.0; 12],
                m: [1.0; VL],
                a: [0.0; VL],
                a_over_m: [0.0; VL],
                pinned: [true; VL],
            };
            for l in 0..rows.x.len() - start {
                let (k, s) = (start + l, 3 * l..3 * l + 3);
                p.x[s.clone()].copy_from_slice(&rows.x[k]);
                p.v[s.clone()].copy_from_slice(&rows.v[k]);
                p.grad[s.clone()].copy_from_slice(&rows.grad[k]);
                if let Some(b) = base {
                    p.xb[s.clone()].copy_from_slice(&b.x[k]);
                    p.vb[s].copy_from_slice(&b.v[k]);
                }
                p.m[l] = rows.mass[k];
                p.a[l] = rows.factor[k];
                p.a_over_m[l] = rows.a_over_m[k];
                p.pinned[l] = rows.pinned[k];
            }
            p
        }
    }

    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn write_trial(
        step: &StepCoefficients,
        rows: &IterateRows,
        base: Option<BaseRows>,
        constraints: bool,
        x_out: &mut [Vec3],
        v_out: &mut [Vec3],
    ) -> TrialSums {
        // SAFETY: as here (by the caller).
        unsafe {
            if rows.unit {
                write_trial_of::<true>(step, rows, base, constraints, x_out, v_out)
            } else {
                write_trial_of::<false>(step, rows, base, constraints, x_out, v_out)
            }
        }
    }

    /// [`write_trial`] with `UNIT == rows.unit` for the full groups (the padded last group takes the general
    /// path: its padding lanes are pinned).
    #[target_feature(enable = "avx2")]
    unsafe fn write_trial_of<const UNIT: bool>(
        step: &StepCoefficients,
        rows: &IterateRows,
        base: Option<BaseRows>,
        constraints: bool,
        x_out: &mut [Vec3],
        v_out: &mut [Vec3],
    ) -> TrialSums {
        let n = rows.x.len();
        let c = Splat {
            lh: _mm256_set1_pd(step.lh),
            alpha: _mm256_set1_pd(step.alpha),
            inv_h2: _mm256_set1_pd(step.inv_h2),
            lp: splat3(step.lp),
            ll: splat3(step.ll),
            lc: splat3(step.lc_over_mt),
            g: splat3(step.gravity),
            center: splat3(step.center),
            h2: _mm256_set1_pd(base.map_or(0.0, |b| b.h2)),
        };
        let mut sums = [_mm256_setzero_pd(); CONSTRAINT_SUMS];
        let mut correction = _mm256_setzero_pd();
        let mut start = 0;
        while start < n {
            let full = start + VL <= n;
            let padded = (!full).then(|| Padded::new(rows, base, start));
            let (gr, xb, vb) = match &padded {
                // SAFETY: start + VL <= n rows of every slice (asserted by the caller).
                None => unsafe {
                    (
                        group::<UNIT>(rows, start),
                        base.map(|b| load_rows(b.x.as_ptr().add(start).cast())),
                        base.map(|b| load_rows(b.v.as_ptr().add(start).cast())),
                    )
                },
                // SAFETY: the padded arrays hold 12 and 4 values.
                Some(p) => unsafe {
                    (
                        Group {
                            x: load_rows(p.x.as_ptr()),
                            v: load_rows(p.v.as_ptr()),
                            grad: load_rows(p.grad.as_ptr()),
                            m: _mm256_loadu_pd(p.m.as_ptr()),
                            a: _mm256_loadu_pd(p.a.as_ptr()),
                            a_over_m: _mm256_loadu_pd(p.a_over_m.as_ptr()),
                            free: free_mask(p.pinned),
                        },
                        base.map(|_| load_rows(p.xb.as_ptr())),
                        base.map(|_| load_rows(p.vb.as_ptr())),
                    )
                },
            };
            let (xo, vo) = if full {
                trial_group::<UNIT>(&c, &gr)
            } else {
                trial_group::<false>(&c, &gr)
            };
            if full {
                // SAFETY: rows start .. start + VL exist in x_out and v_out (asserted by the caller).
                unsafe {
                    store_rows(x_out.as_mut_ptr().add(start).cast(), xo);
                    store_rows(v_out.as_mut_ptr().add(start).cast(), vo);
                }
            } else {
                let (mut px, mut pv) = ([0.0; 12], [0.0; 12]);
                // SAFETY: 12 values each.
                unsafe {
                    store_rows(px.as_mut_ptr(), xo);
                    store_rows(pv.as_mut_ptr(), vo);
                }
                for k in start..n {
                    let l = 3 * (k - start);
                    x_out[k] = [px[l], px[l + 1], px[l + 2]];
                    v_out[k] = [pv[l], pv[l + 1], pv[l + 2]];
                }
            }
            if constraints {
                constraint_group(&mut sums, &xo, &vo, gr.m, &c.g, &c.center);
            }
            if let (Some(xb), Some(vb)) = (xb, vb) {
                let term = if full {
                    correction_group::<UNIT>(&xo, &vo, &xb, &vb, gr.m, gr.a, c.h2)
                } else {
                    correction_group::<false>(&xo, &vo, &xb, &vb, gr.m, gr.a, c.h2)
                };
                correction = add(correction, term);
            }
            start += VL;
        }
        let mut out = [[0.0; VL]; CONSTRAINT_SUMS];
        store(&sums, &mut out);
        let mut corr = [[0.0; VL]];
        store(&[correction], &mut corr);
        TrialSums {
            constraints: constraints.then_some(out),
            correction: base.map(|_| corr[0]),
        }
    }

    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn correction_lanes(
        x: &[Vec3],
        v: &[Vec3],
        base: BaseRows,
        mass: &[f64],
        factor: &[f64],
    ) -> Lane {
        let n = x.len();
        let h2 = _mm256_set1_pd(base.h2);
        let mut acc = _mm256_setzero_pd();
        for start in (0..n).step_by(VL) {
            let term = if start + VL <= n {
                // SAFETY: rows start .. start + VL exist in every slice (asserted by the caller).
                unsafe {
                    let ld = |s: &[Vec3]| load_rows(s.as_ptr().add(start).cast());
                    correction_group::<false>(
                        &ld(x),
                        &ld(v),
                        &ld(base.x),
                        &ld(base.v),
                        _mm256_loadu_pd(mass.as_ptr().add(start)),
                        _mm256_loadu_pd(factor.as_ptr().add(start)),
                        h2,
                    )
                }
            } else {
                let mut p = [[0.0; 12]; 4];
                let (mut m, mut a) = ([1.0; VL], [0.0; VL]);
                for k in start..n {
                    let l = k - start;
                    for (buf, rows) in p.iter_mut().zip([x, v, base.x, base.v]) {
                        buf[3 * l..3 * l + 3].copy_from_slice(&rows[k]);
                    }
                    (m[l], a[l]) = (mass[k], factor[k]);
                }
                // SAFETY: 12 and 4 values.
                unsafe {
                    let [px, pv, pxb, pvb] = p.map(|b| load_rows(b.as_ptr()));
                    let (m, a) = (_mm256_loadu_pd(m.as_ptr()), _mm256_loadu_pd(a.as_ptr()));
                    correction_group::<false>(&px, &pv, &pxb, &pvb, m, a, h2)
                }
            };
            acc = add(acc, term);
        }
        let mut out = [[0.0; VL]];
        store(&[acc], &mut out);
        out[0]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A task's rows: `x`, `v`, `grad`, then the base state's `x`, `v`; masses, factors, `a / m`; pins.
    struct Task {
        arrays: [Vec<Vec3>; 5],
        per_row: [Vec<f64>; 3],
        pinned: Vec<bool>,
    }

    impl Task {
        fn rows(&self) -> IterateRows<'_> {
            let [x, v, grad, ..] = &self.arrays;
            let [mass, factor, a_over_m] = &self.per_row;
            IterateRows {
                x,
                v,
                grad,
                mass,
                factor,
                a_over_m,
                pinned: &self.pinned,
                unit: false,
            }
        }

        fn base(&self, h2: f64) -> BaseRows<'_> {
            let [.., xb, vb] = &self.arrays;
            BaseRows { x: xb, v: vb, h2 }
        }
    }

    /// A task's rows with every kind of value: unequal masses, pinned rows, frozen positions (factor 0),
    /// varied factors, a gradient that does not cancel gravity; and a base state near them.
    fn task(n: usize, seed: u64) -> Task {
        let mut s = seed;
        let mut rnd = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
        };
        let mut vec3s = |scale: f64| -> Vec<Vec3> {
            (0..n)
                .map(|_| [rnd() * scale, rnd() * scale, rnd() * scale])
                .collect()
        };
        let arrays = [vec3s(2.0), vec3s(0.5), vec3s(30.0), vec3s(2.0), vec3s(0.5)];
        let mass: Vec<f64> = (0..n).map(|i| 0.2 + 0.01 * (i % 17) as f64).collect();
        let factor: Vec<f64> = (0..n)
            .map(|i| {
                if i % 11 == 5 {
                    0.0
                } else {
                    1.0 / (1.0 + 0.3 * (i % 5) as f64)
                }
            })
            .collect();
        let a_over_m = factor.iter().zip(&mass).map(|(a, m)| a / m).collect();
        let pinned = (0..n).map(|i| i % 7 == 3).collect();
        Task {
            arrays,
            per_row: [mass, factor, a_over_m],
            pinned,
        }
    }

    fn step() -> StepCoefficients {
        StepCoefficients {
            lh: 0.013,
            alpha: 0.75,
            inv_h2: 1e6,
            lp: [1e-7, -2e-7, 3e-7],
            ll: [-4e-8, 5e-8, 2e-8],
            lc_over_mt: [0.01, -0.02, 0.005],
            gravity: [0.3, -0.2, -9.81],
            center: [0.4, -0.6, 0.5],
        }
    }

    fn bits(values: impl IntoIterator<Item = f64>) -> Vec<u64> {
        values.into_iter().map(f64::to_bits).collect()
    }

    /// The AVX2 kernel on `rows` against the portable reference on `reference_rows` (the same rows, perhaps
    /// without the `unit` hint): the same rows and lane sums, bit for bit. Returns the kernel's sums.
    #[cfg(target_arch = "x86_64")]
    fn avx2_against_portable(
        rows: &IterateRows,
        reference_rows: &IterateRows,
        base: Option<BaseRows>,
        constraints: bool,
    ) -> TrialSums {
        let n = rows.x.len();
        let mut out = [vec![[0.0; 3]; n], vec![[0.0; 3]; n]];
        let mut want = out.clone();
        let [xo, vo] = &mut out;
        // SAFETY: the callers checked that AVX2 is present; every slice has n rows.
        let got = unsafe { avx2::write_trial(&step(), rows, base, constraints, xo, vo) };
        let [xw, vw] = &mut want;
        let reference = portable::write_trial(&step(), reference_rows, base, constraints, xw, vw);
        let flat = |a: &[Vec<Vec3>; 2]| bits(a.iter().flatten().flatten().copied());
        let unit = rows.unit;
        assert_eq!(flat(&out), flat(&want), "rows, {n} rows, unit {unit}");
        let lanes = |s: &TrialSums| {
            let c = s.constraints.iter().flatten().flatten().copied();
            bits(c.chain(s.correction.iter().flatten().copied()))
        };
        assert_eq!(
            lanes(&got),
            lanes(&reference),
            "sums, {n} rows, unit {unit}"
        );
        got
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_trial_matches_the_portable_rows_and_sums_bit_for_bit() {
        if !std::arch::is_x86_feature_detected!("avx2") {
            return;
        }
        // Lengths with every tail (0..3 padding lanes), one row, several groups.
        for n in [1, 2, 3, 4, 5, 6, 7, 8, 61, 64, 65, 130] {
            let t = task(n, n as u64);
            let (rows, base) = (t.rows(), t.base(1e-6));
            let (x, v, mass, factor) = (rows.x, rows.v, rows.mass, rows.factor);
            for (with_base, constraints) in [(true, true), (true, false), (false, true)] {
                let got =
                    avx2_against_portable(&rows, &rows, with_base.then_some(base), constraints);
                assert_eq!(got.constraints.is_some(), constraints);
                assert_eq!(got.correction.is_some(), with_base);
            }
            // SAFETY: as above.
            let c = unsafe { avx2::correction_lanes(x, v, base, mass, factor) };
            let c_ref = portable::correction_lanes(x, v, base, mass, factor);
            assert_eq!(bits(c), bits(c_ref), "D-norm lanes, {n} rows");
        }
    }

    /// On unit rows (no pins, every factor 1), the kernel that skips the factors' products, the division and
    /// the blends gives the portable rows and sums bit for bit, padded last groups included.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_trial_on_unit_rows_keeps_every_bit() {
        if !std::arch::is_x86_feature_detected!("avx2") {
            return;
        }
        for n in [1, 3, 4, 5, 8, 61, 64, 65, 130] {
            let mut t = task(n, 40 + n as u64);
            t.pinned.fill(false);
            let [mass, factor, a_over_m] = &mut t.per_row;
            factor.fill(1.0);
            for (aom, m) in a_over_m.iter_mut().zip(mass.iter()) {
                *aom = 1.0 / m;
            }
            let plain = t.rows();
            let unit = IterateRows {
                unit: true,
                ..plain
            };
            for b in [Some(t.base(1e-6)), None] {
                avx2_against_portable(&unit, &plain, b, true);
            }
        }
    }

    /// The rows are the documented step and the sums are the documented sums (to rounding), pinned rows kept.
    #[test]
    fn the_trial_rows_and_sums_are_the_documented_ones() {
        let n = 23;
        let t = task(n, 9);
        let h2 = 1e-6;
        let (rows, base) = (t.rows(), t.base(h2));
        let (x, v, grad, xb, vb) = (rows.x, rows.v, rows.grad, base.x, base.v);
        let (mass, factor, pinned) = (rows.mass, rows.factor, rows.pinned);
        let c = step();
        let (mut xo, mut vo) = (vec![[0.0; 3]; n], vec![[0.0; 3]; n]);
        let sums = write_trial(&c, &rows, Some(base), true, &mut xo, &mut vo);
        let close =
            |a: f64, b: f64| assert!((a - b).abs() <= 1e-12 * (1.0 + b.abs()), "{a} vs {b}");
        let (mut kinetic, mut correction) = (0.0, 0.0);
        for i in 0..n {
            if pinned[i] {
                assert_eq!((xo[i], vo[i]), (x[i], v[i]), "a pinned row is kept");
            } else {
                // dx = a/m (lambda_H grad U) + a (v x lambda_L + lambda_C / m_tot); dv = (lambda_H v + lambda_P
                // + lambda_L x r) / h^2.
                let r = sub(x[i], c.center);
                let (vxl, lxr) = (cross(v[i], c.ll), cross(c.ll, r));
                for k in 0..3 {
                    let gu = grad[i][k] - mass[i] * c.gravity[k];
                    let dx =
                        factor[i] / mass[i] * c.lh * gu + factor[i] * (vxl[k] + c.lc_over_mt[k]);
                    let dv = (c.lh * v[i][k] + c.lp[k] + lxr[k]) * c.inv_h2;
                    close(xo[i][k], x[i][k] - c.alpha * dx);
                    close(vo[i][k], v[i][k] - c.alpha * dv);
                }
            }
            kinetic += 0.5 * mass[i] * dot(vo[i], vo[i]);
            let (dx, dv) = (sub(xo[i], xb[i]), sub(vo[i], vb[i]));
            let w = if factor[i] > 0.0 {
                mass[i] / factor[i]
            } else {
                0.0
            };
            correction += w * dot(dx, dx) + mass[i] * h2 * dot(dv, dv);
        }
        let lane_sum = crate::projection::lane_sum;
        let constraints = sums.constraints.expect("asked for");
        close(
            lane_sum(&constraints[crate::projection::q::KINETIC]),
            kinetic,
        );
        close(lane_sum(&sums.correction.expect("a base")), correction);
        close(
            lane_sum(&correction_lanes(&xo, &vo, base, mass, factor)),
            correction,
        );
    }
}
