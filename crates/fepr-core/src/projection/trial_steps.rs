//! The projection's trial point over one vertex task (fepr-spec section 3: `q - alpha D^-1 G lambda` with a
//! diagonal position metric), written row by row, and the sums that need only the new rows, taken from them
//! while they are in registers: the constraints' sums (as [`crate::projection::constraint_lanes`] takes
//! them) and the D-norm distance from q~ (as [`correction_lanes`] takes it). The sums run in lanes of [`VL`]
//! rows, each lane in row order, and the caller adds the lanes in lane order: the same bits for any thread
//! count.
//!
//! Two implementations of the same operations: a portable one, and an AVX2 kernel on `pulp`'s four-lane
//! vectors ([`v3`]), picked at run time. Every row and every lane runs the same multiplications, additions and
//! subtractions in the same order (no fused multiply-adds), so both give the same bits (gated by
//! `simd_trial_matches_the_portable_rows_and_sums_bit_for_bit`). Why a kernel: the portable row loop compiles
//! to scalar arithmetic on three-component rows; the kernel transposes four rows into lanes and takes the
//! sums from the new rows while they are in registers.
//!
//! Padding: the last group of a task with fewer than [`VL`] rows gets lanes of unit mass, zero state and zero
//! gradient, pinned and with a zero metric factor, so every sum gets `+0` or `-0` from them and no row is
//! written for them.
//!
//! Length: about 610 lines of code (portable and SIMD versions of the same pass, side by side) and 220 of tests.

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
    if let Some(s) = crate::math::simd::V3::try_new() {
        return v3::write_trial(s, step, rows, base, constraints, x_out, v_out);
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
    if let Some(s) = crate::math::simd::V3::try_new() {
        return v3::correction_lanes(s, x, v, base, mass, factor);
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

/// The same rows and sums in an AVX2 kernel (four lanes per register, through `pulp`'s [`V3`]): every row
/// and lane runs the portable version's operations in its order. Each entry point is compiled with the AVX2
/// features by [`V3::vectorize`]; everything it calls is inlined into it.
#[cfg(target_arch = "x86_64")]
mod v3 {
    use super::*;
    use crate::math::simd::{Kernel, F4, V3};
    use crate::projection::v3::{
        constraint_group, cross_at, load, load_rows, norm2, splat3, store,
    };

    /// Three lane vectors (x, y, z of four rows) written as four rows: the inverse of [`load_rows`].
    #[inline(always)]
    fn store_rows(out: &mut [Vec3], rows: [F4; 3]) {
        let flat: &mut [f64; 12] = out[..VL].as_flattened_mut().try_into().expect("four rows");
        *flat = F4::to_rows3(rows);
    }

    /// One group's input rows in lanes.
    #[derive(Clone, Copy)]
    struct Group {
        x: [F4; 3],
        v: [F4; 3],
        grad: [F4; 3],
        m: F4,
        a: F4,
        a_over_m: F4,
        /// All bits set on a free row's lane, clear on a pinned row's or a padding lane.
        free: F4,
    }

    /// The group of rows `start .. start + VL` (all present); with `UNIT`, every lane free.
    #[inline(always)]
    fn group<const UNIT: bool>(s: V3, rows: &IterateRows, start: usize) -> Group {
        let r = start..start + VL;
        let pinned = if UNIT {
            [false; VL]
        } else {
            rows.pinned[r.clone()].try_into().expect("four rows")
        };
        Group {
            x: load_rows(s, &rows.x[r.clone()]),
            v: load_rows(s, &rows.v[r.clone()]),
            grad: load_rows(s, &rows.grad[r.clone()]),
            m: load(s, &rows.mass[r.clone()]),
            a: load(s, &rows.factor[r.clone()]),
            a_over_m: load(s, &rows.a_over_m[r]),
            free: F4::mask_unless(s, pinned),
        }
    }

    /// The constants of a step in lanes.
    struct Splat {
        lh: F4,
        alpha: F4,
        inv_h2: F4,
        lp: [F4; 3],
        ll: [F4; 3],
        lc: [F4; 3],
        g: [F4; 3],
        center: [F4; 3],
        h2: F4,
    }

    /// The trial rows of a group (a pinned row's lanes keep their rows): [`trial_row`] lane by lane. `UNIT`
    /// (every lane free with `a = 1`): the same bits without the factor's products (`1 x = x`) and the blends.
    #[inline(always)]
    fn trial_group<const UNIT: bool>(c: &Splat, gr: &Group) -> ([F4; 3], [F4; 3]) {
        let r: [F4; 3] = std::array::from_fn(|k| gr.x[k] - c.center[k]);
        let (mut xo, mut vo) = (gr.x, gr.v);
        for k in 0..3 {
            let vxl = cross_at(&gr.v, &c.ll, k);
            let lxr = cross_at(&c.ll, &r, k);
            let gi = gr.grad[k] - gr.m * c.g[k];
            let rigid = vxl + c.lc[k];
            let rigid = if UNIT { rigid } else { gr.a * rigid };
            let dx = c.lh * gi * gr.a_over_m + rigid;
            let dv = (c.lh * gr.v[k] + c.lp[k] + lxr) * c.inv_h2;
            let (x_new, v_new) = (gr.x[k] - c.alpha * dx, gr.v[k] - c.alpha * dv);
            if UNIT {
                (xo[k], vo[k]) = (x_new, v_new);
                continue;
            }
            xo[k] = gr.free.select(x_new, gr.x[k]);
            vo[k] = gr.free.select(v_new, gr.v[k]);
        }
        (xo, vo)
    }

    /// A group's terms of the D-norm distance from `(xb, vb)`: the portable `correction_term` lane by lane.
    /// `UNIT` (`a = 1` on every lane): the same bits without the division (`y / 1 = y`).
    #[inline(always)]
    fn correction_group<const UNIT: bool>(
        x: &[F4; 3],
        v: &[F4; 3],
        xb: &[F4; 3],
        vb: &[F4; 3],
        m: F4,
        a: F4,
        h2: F4,
    ) -> F4 {
        let dx: [F4; 3] = std::array::from_fn(|k| x[k] - xb[k]);
        let dv: [F4; 3] = std::array::from_fn(|k| v[k] - vb[k]);
        // dx^2 / a where a > 0, else 0 (the and clears the lanes of a frozen position, 0/0 included).
        let dx2 = if UNIT {
            norm2(&dx)
        } else {
            (norm2(&dx) / a).and(a.positive())
        };
        m * (dx2 + h2 * norm2(&dv))
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

    /// [`super::write_trial`] compiled for AVX2 (`s` proves the CPU has it).
    pub(super) fn write_trial(
        s: V3,
        step: &StepCoefficients,
        rows: &IterateRows,
        base: Option<BaseRows>,
        constraints: bool,
        x_out: &mut [Vec3],
        v_out: &mut [Vec3],
    ) -> TrialSums {
        if rows.unit {
            s.vectorize(WriteTrial::<true> {
                s,
                step,
                rows,
                base,
                constraints,
                x_out,
                v_out,
            })
        } else {
            s.vectorize(WriteTrial::<false> {
                s,
                step,
                rows,
                base,
                constraints,
                x_out,
                v_out,
            })
        }
    }

    /// [`write_trial`] with `UNIT == rows.unit` for the full groups (the padded last group takes the general
    /// path: its padding lanes are pinned).
    struct WriteTrial<'a, const UNIT: bool> {
        s: V3,
        step: &'a StepCoefficients,
        rows: &'a IterateRows<'a>,
        base: Option<BaseRows<'a>>,
        constraints: bool,
        x_out: &'a mut [Vec3],
        v_out: &'a mut [Vec3],
    }

    impl<const UNIT: bool> Kernel for WriteTrial<'_, UNIT> {
        type Output = TrialSums;
        #[inline(always)]
        fn call(self) -> TrialSums {
            let WriteTrial {
                s,
                step,
                rows,
                base,
                constraints,
                x_out,
                v_out,
            } = self;
            let n = rows.x.len();
            let c = Splat {
                lh: F4::splat(s, step.lh),
                alpha: F4::splat(s, step.alpha),
                inv_h2: F4::splat(s, step.inv_h2),
                lp: splat3(s, step.lp),
                ll: splat3(s, step.ll),
                lc: splat3(s, step.lc_over_mt),
                g: splat3(s, step.gravity),
                center: splat3(s, step.center),
                h2: F4::splat(s, base.map_or(0.0, |b| b.h2)),
            };
            let mut sums = [F4::zero(s); CONSTRAINT_SUMS];
            let mut correction = F4::zero(s);
            let mut start = 0;
            while start < n {
                let full = start + VL <= n;
                let (gr, xb, vb) = if full {
                    let r = start..start + VL;
                    (
                        group::<UNIT>(s, rows, start),
                        base.map(|b| load_rows(s, &b.x[r.clone()])),
                        base.map(|b| load_rows(s, &b.v[r])),
                    )
                } else {
                    let p = Padded::new(rows, base, start);
                    (
                        Group {
                            x: F4::rows3(s, &p.x),
                            v: F4::rows3(s, &p.v),
                            grad: F4::rows3(s, &p.grad),
                            m: F4::from_array(s, p.m),
                            a: F4::from_array(s, p.a),
                            a_over_m: F4::from_array(s, p.a_over_m),
                            free: F4::mask_unless(s, p.pinned),
                        },
                        base.map(|_| F4::rows3(s, &p.xb)),
                        base.map(|_| F4::rows3(s, &p.vb)),
                    )
                };
                let (xo, vo) = if full {
                    trial_group::<UNIT>(&c, &gr)
                } else {
                    trial_group::<false>(&c, &gr)
                };
                if full {
                    store_rows(&mut x_out[start..start + VL], xo);
                    store_rows(&mut v_out[start..start + VL], vo);
                } else {
                    let (px, pv) = (F4::to_rows3(xo), F4::to_rows3(vo));
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
                    correction = correction + term;
                }
                start += VL;
            }
            let mut out = [[0.0; VL]; CONSTRAINT_SUMS];
            store(&sums, &mut out);
            TrialSums {
                constraints: constraints.then_some(out),
                correction: base.map(|_| correction.to_array()),
            }
        }
    }

    /// [`super::correction_lanes`] compiled for AVX2 (`s` proves the CPU has it).
    pub(super) fn correction_lanes(
        s: V3,
        x: &[Vec3],
        v: &[Vec3],
        base: BaseRows,
        mass: &[f64],
        factor: &[f64],
    ) -> Lane {
        struct Op<'a> {
            s: V3,
            x: &'a [Vec3],
            v: &'a [Vec3],
            base: BaseRows<'a>,
            mass: &'a [f64],
            factor: &'a [f64],
        }
        impl Kernel for Op<'_> {
            type Output = Lane;
            #[inline(always)]
            fn call(self) -> Lane {
                let Op {
                    s,
                    x,
                    v,
                    base,
                    mass,
                    factor,
                } = self;
                let n = x.len();
                let h2 = F4::splat(s, base.h2);
                let mut acc = F4::zero(s);
                for start in (0..n).step_by(VL) {
                    let term = if start + VL <= n {
                        let r = start..start + VL;
                        correction_group::<false>(
                            &load_rows(s, &x[r.clone()]),
                            &load_rows(s, &v[r.clone()]),
                            &load_rows(s, &base.x[r.clone()]),
                            &load_rows(s, &base.v[r.clone()]),
                            load(s, &mass[r.clone()]),
                            load(s, &factor[r]),
                            h2,
                        )
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
                        let [px, pv, pxb, pvb] = p.map(|b| F4::rows3(s, &b));
                        let (m, a) = (F4::from_array(s, m), F4::from_array(s, a));
                        correction_group::<false>(&px, &pv, &pxb, &pvb, m, a, h2)
                    };
                    acc = acc + term;
                }
                acc.to_array()
            }
        }
        s.vectorize(Op {
            s,
            x,
            v,
            base,
            mass,
            factor,
        })
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
    fn simd_against_portable(
        rows: &IterateRows,
        reference_rows: &IterateRows,
        base: Option<BaseRows>,
        constraints: bool,
    ) -> TrialSums {
        let n = rows.x.len();
        let mut out = [vec![[0.0; 3]; n], vec![[0.0; 3]; n]];
        let mut want = out.clone();
        let [xo, vo] = &mut out;
        let s = crate::math::simd::V3::try_new().expect("checked by the callers");
        let got = v3::write_trial(s, &step(), rows, base, constraints, xo, vo);
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
    fn simd_trial_matches_the_portable_rows_and_sums_bit_for_bit() {
        if crate::math::simd::V3::try_new().is_none() {
            return;
        }
        // Lengths with every tail (0..3 padding lanes), one row, several groups.
        for n in [1, 2, 3, 4, 5, 6, 7, 8, 61, 64, 65, 130] {
            let t = task(n, n as u64);
            let (rows, base) = (t.rows(), t.base(1e-6));
            let (x, v, mass, factor) = (rows.x, rows.v, rows.mass, rows.factor);
            for (with_base, constraints) in [(true, true), (true, false), (false, true)] {
                let got =
                    simd_against_portable(&rows, &rows, with_base.then_some(base), constraints);
                assert_eq!(got.constraints.is_some(), constraints);
                assert_eq!(got.correction.is_some(), with_base);
            }
            let s = crate::math::simd::V3::try_new().expect("checked above");
            let c = v3::correction_lanes(s, x, v, base, mass, factor);
            let c_ref = portable::correction_lanes(x, v, base, mass, factor);
            assert_eq!(bits(c), bits(c_ref), "D-norm lanes, {n} rows");
        }
    }

    /// On unit rows (no pins, every factor 1), the kernel that skips the factors' products, the division and
    /// the blends gives the portable rows and sums bit for bit, padded last groups included.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn simd_trial_on_unit_rows_keeps_every_bit() {
        if crate::math::simd::V3::try_new().is_none() {
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
                simd_against_portable(&unit, &plain, b, true);
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
