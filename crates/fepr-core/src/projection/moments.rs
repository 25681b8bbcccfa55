//! The projection's per-vertex sums (fepr-spec section 3: the constraint values and the mass moments that
//! form `S`) over one task's rows, in structure-of-arrays lanes: [`VL`] vertices at a time, each lane summed
//! on its own in vertex order. The caller adds the lanes in lane order, so the order of every sum is fixed
//! and the results keep their bits for any thread count.
//!
//! Two implementations of the same operations: a portable one, and AVX2 kernels on `pulp`'s four-lane
//! vectors ([`v3`]), picked at run time. Both run every lane's multiplications, additions and subtractions
//! in the same order (no fused multiply-adds), so they give the same bits (gated by
//! `simd_kernels_match_the_portable_sums_bit_for_bit`). Why separate kernels: the portable loops compile to
//! shuffles of scalars and spilled accumulators (the 45 sums for `S` do not fit 16 vector registers); the
//! kernels load each group of rows once, transposed into lanes, and sum in passes of at most 12
//! accumulators.
//!
//! Padding: the last group of a task with fewer than [`VL`] rows gets lanes of unit mass, zero state and
//! zero gradient, neither free nor weighted, so every sum gets `+0` or `-0` from them.
//!
//! Length: about 890 lines of code because every sum exists twice, portable and in SIMD lanes, side by side so
//! that the operation-by-operation correspondence (the bit-for-bit contract) can be read; tests compare the two.

use crate::math::Vec3;

/// Vertices per lane group.
pub(crate) const VL: usize = 4;
/// One value per lane.
pub(crate) type Lane = [f64; VL];

/// The per-vertex sums, as indices into the lane accumulators of [`moment_lanes`] (the first
/// [`CONSTRAINT_SUMS`] are those of [`constraint_lanes`]).
pub(crate) mod q {
    pub const KINETIC: usize = 0;
    pub const GRAVITATIONAL: usize = 1;
    pub const MOMENTUM: usize = 2; // 3
    pub const ANGULAR: usize = 5; // 3
    pub const MASS_X: usize = 8; // 3
    pub const FREE_MASS: usize = 11;
    pub const A_FREE_MASS: usize = 12;
    pub const GRAD_SQ_OVER_W: usize = 13;
    pub const TR_VV: usize = 14;
    pub const A_GRAD_SUM: usize = 15; // 3
    pub const A_GRAD_CROSS_V: usize = 18; // 3
    pub const FREE_P: usize = 21; // 3
    pub const A_FREE_P: usize = 24; // 3
    pub const FREE_L: usize = 27; // 3
    pub const FREE_R: usize = 30; // 3
    pub const A_VV: usize = 33; // 6: the upper triangle, row by row
    pub const RR: usize = 39; // 6
    pub const COUNT: usize = 45;
}

/// The sums of [`constraint_lanes`]: kinetic and gravitational energy, momentum, angular momentum about
/// the target centre of mass, `sum m x`.
pub(crate) const CONSTRAINT_SUMS: usize = q::MASS_X + 3;

/// The second-order sums of [`moment_and_second_order_lanes`]: `sum a g r^T` (9, row by row), `sum a m r x v`
/// (3), `sum a m r` (3).
pub(crate) const SECOND_ORDER_SUMS: usize = 15;

/// The upper triangle of a symmetric 3x3 matrix, row by row (`a <= b`).
pub(crate) const UPPER: [(usize, usize); 6] = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)];

/// One task's rows: vertex `k` of the task is `x[k]`, `v[k]`, ... (all the same length).
#[derive(Clone, Copy)]
pub(crate) struct Rows<'a> {
    /// Positions (m).
    pub x: &'a [Vec3],
    /// Velocities (m/s).
    pub v: &'a [Vec3],
    /// The elastic gradient (J/m); the potential's is this minus `m g`. Without it, zero: the moments that
    /// do not involve the gradient (the warm start's) are exact, the others are not to be solved with.
    pub grad: Option<&'a [Vec3]>,
    /// Masses (kg).
    pub mass: &'a [f64],
    /// The mass of a free vertex, 0 for a pinned one.
    pub free_mass: &'a [f64],
    /// The metric factor `a` of a free vertex, 0 for a pinned one.
    pub free_factor: &'a [f64],
    /// Every row is free with a unit factor (`free_mass == mass`, `free_factor == 1`): the mass metric on a
    /// body without pins or frozen positions. The kernels then skip the sums that repeat others bit for bit
    /// (see [`v3`]); the results are the same bits either way.
    pub unit: bool,
}

impl Rows<'_> {
    /// Panics unless every slice has one row per vertex (the kernels read them unchecked).
    fn assert_lengths(&self) {
        let n = self.x.len();
        assert!(
            [
                self.v.len(),
                self.grad.map_or(n, |g| g.len()),
                self.mass.len(),
                self.free_mass.len(),
                self.free_factor.len()
            ]
            .iter()
            .all(|&k| k == n),
            "one row per vertex"
        );
        debug_assert!(
            !self.unit
                || (self.free_factor.iter().all(|&a| a == 1.0)
                    && self
                        .free_mass
                        .iter()
                        .zip(self.mass)
                        .all(|(f, m)| f.to_bits() == m.to_bits())),
            "unit rows are free with a unit factor"
        );
    }
}

/// The constraints' sums of the rows `x`, `v`, `mass` (indexed as [`q`], `KINETIC .. MASS_X + 2`), with
/// gravity `g` (m/s^2) and the angular momentum about `center` (m).
pub(crate) fn constraint_lanes(
    x: &[Vec3],
    v: &[Vec3],
    mass: &[f64],
    g: Vec3,
    center: Vec3,
) -> [Lane; CONSTRAINT_SUMS] {
    assert!(
        v.len() == x.len() && mass.len() == x.len(),
        "one row per vertex"
    );
    #[cfg(target_arch = "x86_64")]
    if let Some(s) = crate::math::simd::V3::try_new() {
        return v3::constraint_lanes(s, x, v, mass, g, center);
    }
    portable::constraint_lanes(x, v, mass, g, center)
}

/// All the sums of [`q`] over `rows`: the constraints' and the moments for `S`.
pub(crate) fn moment_lanes(rows: &Rows, g: Vec3, center: Vec3) -> [Lane; q::COUNT] {
    rows.assert_lengths();
    #[cfg(target_arch = "x86_64")]
    if let Some(s) = crate::math::simd::V3::try_new() {
        return v3::moment_lanes(s, rows, g, center);
    }
    portable::moment_lanes(rows, g, center)
}

/// All the sums of [`q`] over `rows` ([`moment_lanes`]) and the angular momentum's second-order moments, with
/// `r = x - center` and `g_i` the potential's gradient (see [`SECOND_ORDER_SUMS`]), in one sweep over the rows.
pub(crate) fn moment_and_second_order_lanes(
    rows: &Rows,
    g: Vec3,
    center: Vec3,
) -> ([Lane; q::COUNT], [Lane; SECOND_ORDER_SUMS]) {
    rows.assert_lengths();
    #[cfg(target_arch = "x86_64")]
    if let Some(s) = crate::math::simd::V3::try_new() {
        return v3::moment_and_second_order_lanes(s, rows, g, center);
    }
    (
        portable::moment_lanes(rows, g, center),
        portable::second_order_lanes(rows, g, center),
    )
}

/// One sum's lanes added in lane order (a fixed order: the result does not depend on which threads ran the
/// tasks).
#[inline]
pub(crate) fn lane_sum(lane: &Lane) -> f64 {
    lane.iter().fold(0.0, |s, a| s + a)
}

/// The reference implementation, for any CPU.
pub(crate) mod portable {
    use super::*;

    /// A lane group from its per-lane values.
    #[inline(always)]
    fn lanes(f: impl Fn(usize) -> f64) -> Lane {
        std::array::from_fn(f)
    }

    /// The potential's gradient at one vertex: the elastic gradient minus the gravity force `m g`.
    #[inline(always)]
    fn total_gradient(elastic: Vec3, mass: f64, gravity: Vec3) -> Vec3 {
        [
            elastic[0] - mass * gravity[0],
            elastic[1] - mass * gravity[1],
            elastic[2] - mass * gravity[2],
        ]
    }

    /// One lane group's terms of the constraints' sums, and the `|v|^2`, `r = x - center` and `r x v` they
    /// are made of (the moments for `S` reuse them).
    #[inline(always)]
    fn constraint_terms(
        xs: [Lane; 3],
        vs: [Lane; 3],
        m: Lane,
        g: Vec3,
        center: Vec3,
    ) -> ([Lane; CONSTRAINT_SUMS], Lane, [Lane; 3], [Lane; 3]) {
        let vv = lanes(|l| vs[0][l] * vs[0][l] + vs[1][l] * vs[1][l] + vs[2][l] * vs[2][l]);
        let r: [Lane; 3] = std::array::from_fn(|a| lanes(|l| xs[a][l] - center[a]));
        let rxv: [Lane; 3] = std::array::from_fn(|a| {
            let (b, c) = ((a + 1) % 3, (a + 2) % 3);
            lanes(|l| r[b][l] * vs[c][l] - r[c][l] * vs[b][l])
        });
        let mut t = [[0.0; VL]; CONSTRAINT_SUMS];
        t[q::KINETIC] = lanes(|l| 0.5 * m[l] * vv[l]);
        t[q::GRAVITATIONAL] =
            lanes(|l| -(m[l] * (g[0] * xs[0][l] + g[1] * xs[1][l] + g[2] * xs[2][l])));
        for a in 0..3 {
            t[q::MOMENTUM + a] = lanes(|l| m[l] * vs[a][l]);
            t[q::ANGULAR + a] = lanes(|l| m[l] * rxv[a][l]);
            t[q::MASS_X + a] = lanes(|l| m[l] * xs[a][l]);
        }
        (t, vv, r, rxv)
    }

    /// One group's lanes: rows `start ..` (padded past `n`).
    struct Group {
        x: [Lane; 3],
        v: [Lane; 3],
        /// The potential's gradient.
        g: [Lane; 3],
        m: Lane,
        mf: Lane,
        af: Lane,
        /// Which lanes hold a row.
        real: [bool; VL],
    }

    fn group(rows: &Rows, start: usize, gravity: Vec3) -> Group {
        let mut gr = Group {
            x: [[0.0; VL]; 3],
            v: [[0.0; VL]; 3],
            g: [[0.0; VL]; 3],
            m: [1.0; VL],
            mf: [0.0; VL],
            af: [0.0; VL],
            real: [false; VL],
        };
        for l in 0..VL.min(rows.x.len() - start) {
            let k = start + l;
            let elastic = rows.grad.map_or([0.0; 3], |g| g[k]);
            let gi = total_gradient(elastic, rows.mass[k], gravity);
            gr.m[l] = rows.mass[k];
            gr.mf[l] = rows.free_mass[k];
            gr.af[l] = rows.free_factor[k];
            gr.real[l] = true;
            for a in 0..3 {
                gr.x[a][l] = rows.x[k][a];
                gr.v[a][l] = rows.v[k][a];
                gr.g[a][l] = gi[a];
            }
        }
        gr
    }

    #[inline(always)]
    fn add(acc: &mut Lane, value: Lane) {
        for l in 0..VL {
            acc[l] += value[l];
        }
    }

    pub(crate) fn constraint_lanes(
        x: &[Vec3],
        v: &[Vec3],
        mass: &[f64],
        g: Vec3,
        center: Vec3,
    ) -> [Lane; CONSTRAINT_SUMS] {
        let n = x.len();
        let mut acc = [[0.0; VL]; CONSTRAINT_SUMS];
        for start in (0..n).step_by(VL) {
            let (mut xs, mut vs, mut m) = ([[0.0; VL]; 3], [[0.0; VL]; 3], [1.0; VL]);
            for l in 0..VL.min(n - start) {
                m[l] = mass[start + l];
                for a in 0..3 {
                    xs[a][l] = x[start + l][a];
                    vs[a][l] = v[start + l][a];
                }
            }
            let (terms, ..) = constraint_terms(xs, vs, m, g, center);
            for (a, t) in acc.iter_mut().zip(terms) {
                add(a, t);
            }
        }
        acc
    }

    pub(crate) fn moment_lanes(rows: &Rows, gravity: Vec3, center: Vec3) -> [Lane; q::COUNT] {
        let mut acc = [[0.0; VL]; q::COUNT];
        for start in (0..rows.x.len()).step_by(VL) {
            let Group {
                x: xs,
                v: vs,
                g: gs,
                m,
                mf,
                af,
                ..
            } = group(rows, start, gravity);
            let gxv: [Lane; 3] = std::array::from_fn(|a| {
                let (b, c) = ((a + 1) % 3, (a + 2) % 3);
                lanes(|l| gs[b][l] * vs[c][l] - gs[c][l] * vs[b][l])
            });
            let (terms, vv, r, rxv) = constraint_terms(xs, vs, m, gravity, center);
            for (k, t) in terms.into_iter().enumerate() {
                add(&mut acc[k], t);
            }
            let am = lanes(|l| af[l] * m[l]);
            add(&mut acc[q::FREE_MASS], mf);
            add(&mut acc[q::A_FREE_MASS], am);
            add(
                &mut acc[q::GRAD_SQ_OVER_W],
                lanes(|l| {
                    af[l] * (gs[0][l] * gs[0][l] + gs[1][l] * gs[1][l] + gs[2][l] * gs[2][l]) / m[l]
                }),
            );
            add(&mut acc[q::TR_VV], lanes(|l| mf[l] * vv[l]));
            for a in 0..3 {
                add(&mut acc[q::A_GRAD_SUM + a], lanes(|l| af[l] * gs[a][l]));
                add(
                    &mut acc[q::A_GRAD_CROSS_V + a],
                    lanes(|l| af[l] * gxv[a][l]),
                );
                add(&mut acc[q::FREE_P + a], lanes(|l| mf[l] * vs[a][l]));
                add(&mut acc[q::A_FREE_P + a], lanes(|l| am[l] * vs[a][l]));
                add(&mut acc[q::FREE_L + a], lanes(|l| mf[l] * rxv[a][l]));
                add(&mut acc[q::FREE_R + a], lanes(|l| mf[l] * r[a][l]));
            }
            for (k, &(a, b)) in UPPER.iter().enumerate() {
                add(
                    &mut acc[q::A_VV + k],
                    lanes(|l| am[l] * vs[a][l] * vs[b][l]),
                );
                add(&mut acc[q::RR + k], lanes(|l| mf[l] * r[a][l] * r[b][l]));
            }
        }
        acc
    }

    pub(crate) fn second_order_lanes(
        rows: &Rows,
        gravity: Vec3,
        center: Vec3,
    ) -> [Lane; SECOND_ORDER_SUMS] {
        let mut acc = [[0.0; VL]; SECOND_ORDER_SUMS];
        for start in (0..rows.x.len()).step_by(VL) {
            let gr = group(rows, start, gravity);
            let (gs, vs, af) = (gr.g, gr.v, gr.af);
            let am = lanes(|l| af[l] * gr.m[l]);
            // r = x - center on a row, 0 on a padding lane.
            let rs: [Lane; 3] = std::array::from_fn(|a| {
                lanes(|l| {
                    if gr.real[l] {
                        gr.x[a][l] - center[a]
                    } else {
                        0.0
                    }
                })
            });
            for c in 0..3 {
                let (b, d) = ((c + 1) % 3, (c + 2) % 3);
                for e in 0..3 {
                    add(&mut acc[3 * c + e], lanes(|l| af[l] * gs[c][l] * rs[e][l]));
                }
                add(
                    &mut acc[9 + c],
                    lanes(|l| am[l] * (rs[b][l] * vs[d][l] - rs[d][l] * vs[b][l])),
                );
                add(&mut acc[12 + c], lanes(|l| am[l] * rs[c][l]));
            }
        }
        acc
    }
}

/// The same sums in AVX2 kernels (four lanes per register, through `pulp`'s [`V3`]): every lane runs the
/// portable version's operations in its order. The 45 sums for `S` run as four passes over the task's rows
/// (10-12 accumulators each, about what 16 vector registers hold), the second-order ones as two more; the
/// task's rows stay in L1/L2 between passes. Each entry point is compiled with the AVX2 features by
/// [`V3::vectorize`]; everything it calls is inlined into it.
#[cfg(target_arch = "x86_64")]
pub(crate) mod v3 {
    use super::*;
    use crate::math::simd::{Kernel, F4, V3};

    /// Four rows of three `f64` as three lane vectors (x, y, z).
    #[inline(always)]
    pub(crate) fn load_rows(s: V3, rows: &[Vec3]) -> [F4; 3] {
        let flat: &[f64; 12] = rows[..VL].as_flattened().try_into().expect("four rows");
        F4::rows3(s, flat)
    }

    /// Four values as lanes.
    #[inline(always)]
    pub(crate) fn load(s: V3, values: &[f64]) -> F4 {
        F4::from_array(s, values[..VL].try_into().expect("four values"))
    }

    #[inline(always)]
    pub(crate) fn splat3(s: V3, v: Vec3) -> [F4; 3] {
        v.map(|c| F4::splat(s, c))
    }

    /// `|v|^2` as the portable version sums it.
    #[inline(always)]
    pub(crate) fn norm2(v: &[F4; 3]) -> F4 {
        v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    }

    /// Component `a` of `p x q` (`p_b q_c - p_c q_b`).
    #[inline(always)]
    pub(crate) fn cross_at(p: &[F4; 3], q: &[F4; 3], a: usize) -> F4 {
        let (b, c) = ((a + 1) % 3, (a + 2) % 3);
        p[b] * q[c] - p[c] * q[b]
    }

    /// One group's rows in lanes (padded as the portable version pads).
    #[derive(Clone, Copy)]
    struct Group {
        x: [F4; 3],
        v: [F4; 3],
        /// The elastic gradient (the potential's is formed by [`potential_gradient`]).
        grad: [F4; 3],
        m: F4,
        mf: F4,
        af: F4,
        /// All bits set on a lane that holds a row, clear on a padding lane.
        real: F4,
    }

    impl Group {
        #[inline(always)]
        fn zero(s: V3) -> Self {
            let z = F4::zero(s);
            Group {
                x: [z; 3],
                v: [z; 3],
                grad: [z; 3],
                m: z,
                mf: z,
                af: z,
                real: z,
            }
        }
    }

    /// The group of rows `start .. start + VL` (all present), or the padded last group.
    #[inline(always)]
    fn group(s: V3, rows: &Rows, start: usize) -> Group {
        if start + VL > rows.x.len() {
            let p = Padded::new(rows, start);
            return Group {
                x: F4::rows3(s, &p.x),
                v: F4::rows3(s, &p.v),
                grad: F4::rows3(s, &p.grad),
                m: F4::from_array(s, p.m),
                mf: F4::from_array(s, p.mf),
                af: F4::from_array(s, p.af),
                real: F4::mask_unless(s, p.padding),
            };
        }
        let r = start..start + VL;
        Group {
            x: load_rows(s, &rows.x[r.clone()]),
            v: load_rows(s, &rows.v[r.clone()]),
            grad: match rows.grad {
                Some(g) => load_rows(s, &g[r.clone()]),
                None => [F4::zero(s); 3],
            },
            m: load(s, &rows.mass[r.clone()]),
            mf: load(s, &rows.free_mass[r.clone()]),
            af: load(s, &rows.free_factor[r]),
            real: F4::all_bits(s),
        }
    }

    /// The last group's rows with the padding lanes' values (zero state and gradient, unit mass, neither
    /// free nor weighted).
    struct Padded {
        x: [f64; 12],
        v: [f64; 12],
        grad: [f64; 12],
        m: [f64; VL],
        mf: [f64; VL],
        af: [f64; VL],
        padding: [bool; VL],
    }

    impl Padded {
        /// The last group of rows `start ..` (fewer than [`VL`]). Out of line: the loop over the full groups
        /// stays small enough to be inlined whole.
        #[cold]
        #[inline(never)]
        fn new(rows: &Rows, start: usize) -> Self {
            let mut pad = Self {
                x: [0.0; 12],
                v: [0.0; 12],
                grad: [0.0; 12],
                m: [1.0; VL],
                mf: [0.0; VL],
                af: [0.0; VL],
                padding: [true; VL],
            };
            for l in 0..rows.x.len() - start {
                let k = start + l;
                pad.x[3 * l..3 * l + 3].copy_from_slice(&rows.x[k]);
                pad.v[3 * l..3 * l + 3].copy_from_slice(&rows.v[k]);
                if let Some(g) = rows.grad {
                    pad.grad[3 * l..3 * l + 3].copy_from_slice(&g[k]);
                }
                pad.m[l] = rows.mass[k];
                pad.mf[l] = rows.free_mass[k];
                pad.af[l] = rows.free_factor[k];
                pad.padding[l] = false;
            }
            pad
        }
    }

    /// The potential's gradient `grad - m g` on a row, 0 on a padding lane.
    #[inline(always)]
    fn potential_gradient(gr: &Group, gravity: &[F4; 3]) -> [F4; 3] {
        std::array::from_fn(|a| (gr.grad[a] - gr.m * gravity[a]).and(gr.real))
    }

    /// The accumulators' lanes.
    #[inline(always)]
    pub(crate) fn store<const N: usize>(acc: &[F4; N], out: &mut [Lane]) {
        for (o, a) in out.iter_mut().zip(acc) {
            *o = a.to_array();
        }
    }

    /// One group's constraint terms added to `acc` (the portable `constraint_terms`, operation by
    /// operation).
    #[inline(always)]
    pub(crate) fn constraint_group(
        acc: &mut [F4; CONSTRAINT_SUMS],
        xs: &[F4; 3],
        vs: &[F4; 3],
        m: F4,
        g: &[F4; 3],
        center: &[F4; 3],
    ) {
        let half = F4::splat(m.simd(), 0.5);
        let vv = norm2(vs);
        let r: [F4; 3] = std::array::from_fn(|a| xs[a] - center[a]);
        acc[q::KINETIC] = acc[q::KINETIC] + half * m * vv;
        let gx = g[0] * xs[0] + g[1] * xs[1] + g[2] * xs[2];
        acc[q::GRAVITATIONAL] = acc[q::GRAVITATIONAL] + -(m * gx);
        for a in 0..3 {
            acc[q::MOMENTUM + a] = acc[q::MOMENTUM + a] + m * vs[a];
            acc[q::ANGULAR + a] = acc[q::ANGULAR + a] + m * cross_at(&r, vs, a);
            acc[q::MASS_X + a] = acc[q::MASS_X + a] + m * xs[a];
        }
    }

    /// [`super::constraint_lanes`] compiled for AVX2 (`s` proves the CPU has it).
    pub(crate) fn constraint_lanes(
        s: V3,
        x: &[Vec3],
        v: &[Vec3],
        mass: &[f64],
        g: Vec3,
        center: Vec3,
    ) -> [Lane; CONSTRAINT_SUMS] {
        struct Op<'a> {
            s: V3,
            x: &'a [Vec3],
            v: &'a [Vec3],
            mass: &'a [f64],
            g: Vec3,
            center: Vec3,
        }
        impl Kernel for Op<'_> {
            type Output = [Lane; CONSTRAINT_SUMS];
            #[inline(always)]
            fn call(self) -> Self::Output {
                let Op {
                    s,
                    x,
                    v,
                    mass,
                    g,
                    center,
                } = self;
                let n = x.len();
                let (gv, cv) = (splat3(s, g), splat3(s, center));
                let mut acc = [F4::zero(s); CONSTRAINT_SUMS];
                for start in (0..n).step_by(VL) {
                    let (xs, vs, m) = if start + VL <= n {
                        let r = start..start + VL;
                        (
                            load_rows(s, &x[r.clone()]),
                            load_rows(s, &v[r.clone()]),
                            load(s, &mass[r]),
                        )
                    } else {
                        let (mut px, mut pv, mut pm) = ([0.0; 12], [0.0; 12], [1.0; VL]);
                        for l in 0..n - start {
                            px[3 * l..3 * l + 3].copy_from_slice(&x[start + l]);
                            pv[3 * l..3 * l + 3].copy_from_slice(&v[start + l]);
                            pm[l] = mass[start + l];
                        }
                        (F4::rows3(s, &px), F4::rows3(s, &pv), F4::from_array(s, pm))
                    };
                    constraint_group(&mut acc, &xs, &vs, m, &gv, &cv);
                }
                let mut out = [[0.0; VL]; CONSTRAINT_SUMS];
                store(&acc, &mut out);
                out
            }
        }
        s.vectorize(Op {
            s,
            x,
            v,
            mass,
            g,
            center,
        })
    }

    /// Groups per block of [`for_blocks`]: 16 groups of four rows (6.5 KiB of lanes) stay in L1 while every
    /// pass runs over them.
    const BLOCK_GROUPS: usize = 16;

    /// Runs `f` on the groups of `rows` in blocks of up to [`BLOCK_GROUPS`] consecutive groups, each group
    /// loaded (transposed into lanes) once per block. The passes then run over the block's groups in order:
    /// each lane's sum still takes its rows in row order, so the bits are those of one pass over all rows at
    /// a time. Loading a group costs about twenty shuffles, and there are six passes.
    #[inline(always)]
    fn for_blocks(s: V3, rows: &Rows, mut f: impl FnMut(&[Group])) {
        let n = rows.x.len();
        let mut block = [Group::zero(s); BLOCK_GROUPS];
        let mut start = 0;
        while start < n {
            let count = (n - start).div_ceil(VL).min(BLOCK_GROUPS);
            for (j, slot) in block[..count].iter_mut().enumerate() {
                *slot = group(s, rows, start + j * VL);
            }
            f(&block[..count]);
            start += count * VL;
        }
    }

    /// `$body` for each group `$gr` of `$groups` in order, on the accumulators `$acc` (as `$a`) held in
    /// registers meanwhile. A macro, not a function taking a closure: a closure called from two
    /// instances is compiled out of line, without the caller's target features.
    macro_rules! over {
        ($acc:expr, $groups:expr, |$a:ident, $gr:ident| $body:block) => {{
            let mut acc = $acc;
            for $gr in $groups {
                let $a = &mut acc;
                $body
            }
            $acc = acc;
        }};
    }

    /// The accumulators of [`moment_lanes`], by pass.
    struct MomentAcc {
        constraints: [F4; CONSTRAINT_SUMS],
        /// FREE_MASS, A_FREE_MASS, GRAD_SQ_OVER_W, TR_VV, A_GRAD_SUM (3), A_GRAD_CROSS_V (3).
        gradient: [F4; 10],
        /// FREE_P, A_FREE_P, FREE_L, FREE_R (3 each).
        free: [F4; 12],
        /// A_VV, RR (the upper triangles).
        outer: [F4; 12],
    }

    impl MomentAcc {
        #[inline(always)]
        fn zero(s: V3) -> Self {
            let z = F4::zero(s);
            MomentAcc {
                constraints: [z; CONSTRAINT_SUMS],
                gradient: [z; 10],
                free: [z; 12],
                outer: [z; 12],
            }
        }
    }

    /// The accumulators of the second-order moments, by pass.
    struct SecondOrderAcc {
        /// `sum a g r^T`, row by row.
        grad_r: [F4; 9],
        /// `sum a m r x v`, `sum a m r`.
        mass_r: [F4; 6],
    }

    impl SecondOrderAcc {
        #[inline(always)]
        fn zero(s: V3) -> Self {
            let z = F4::zero(s);
            SecondOrderAcc {
                grad_r: [z; 9],
                mass_r: [z; 6],
            }
        }
    }

    /// The four passes of the moments for `S` over one block's groups. `UNIT` ([`Rows::unit`]): every row
    /// is free with `a = 1`, so `a m = m` and `a g = g` exactly, and these sums repeat others bit for bit:
    /// `A_FREE_MASS` is `FREE_MASS`, `FREE_P` and `A_FREE_P` are `MOMENTUM`, `FREE_L` is `ANGULAR` (the same
    /// products added in the same order; a padding lane adds `+0` or `-0` to either, which leaves a sum that
    /// started at `+0` unchanged). Those are copied by [`store_moments`], and the factors of one are not
    /// multiplied.
    #[inline(always)]
    fn moment_passes<const UNIT: bool>(
        acc: &mut MomentAcc,
        groups: &[Group],
        gv: &[F4; 3],
        cv: &[F4; 3],
    ) {
        over!(acc.constraints, groups, |acc, gr| {
            constraint_group(acc, &gr.x, &gr.v, gr.m, gv, cv)
        });
        over!(acc.gradient, groups, |acc, gr| {
            let gs = potential_gradient(gr, gv);
            acc[0] = acc[0] + gr.mf;
            acc[3] = acc[3] + gr.mf * norm2(&gr.v);
            if UNIT {
                acc[2] = acc[2] + norm2(&gs) / gr.m;
                for a in 0..3 {
                    acc[4 + a] = acc[4 + a] + gs[a];
                    acc[7 + a] = acc[7 + a] + cross_at(&gs, &gr.v, a);
                }
                continue;
            }
            let am = gr.af * gr.m;
            acc[1] = acc[1] + am;
            acc[2] = acc[2] + gr.af * norm2(&gs) / gr.m;
            for a in 0..3 {
                acc[4 + a] = acc[4 + a] + gr.af * gs[a];
                acc[7 + a] = acc[7 + a] + gr.af * cross_at(&gs, &gr.v, a);
            }
        });
        over!(acc.free, groups, |acc, gr| {
            let r: [F4; 3] = std::array::from_fn(|a| gr.x[a] - cv[a]);
            if UNIT {
                for a in 0..3 {
                    acc[9 + a] = acc[9 + a] + gr.mf * r[a];
                }
                continue;
            }
            let am = gr.af * gr.m;
            for a in 0..3 {
                acc[a] = acc[a] + gr.mf * gr.v[a];
                acc[3 + a] = acc[3 + a] + am * gr.v[a];
                acc[6 + a] = acc[6 + a] + gr.mf * cross_at(&r, &gr.v, a);
                acc[9 + a] = acc[9 + a] + gr.mf * r[a];
            }
        });
        over!(acc.outer, groups, |acc, gr| {
            let am = if UNIT { gr.m } else { gr.af * gr.m };
            let r: [F4; 3] = std::array::from_fn(|a| gr.x[a] - cv[a]);
            for (k, &(a, b)) in UPPER.iter().enumerate() {
                acc[k] = acc[k] + am * gr.v[a] * gr.v[b];
                acc[6 + k] = acc[6 + k] + gr.mf * r[a] * r[b];
            }
        });
    }

    /// The two passes of the second-order moments over one block's groups. `UNIT` (see [`moment_passes`]):
    /// `sum a m r x v` is `ANGULAR` and `sum a m r` is `FREE_R` bit for bit (`r` is masked to 0 on a padding
    /// lane here, and multiplied by a zero free mass there), copied by [`store_second_order`].
    #[inline(always)]
    fn second_order_passes<const UNIT: bool>(
        acc: &mut SecondOrderAcc,
        groups: &[Group],
        gv: &[F4; 3],
        cv: &[F4; 3],
    ) {
        over!(acc.grad_r, groups, |acc, gr| {
            let gs = potential_gradient(gr, gv);
            let r: [F4; 3] = std::array::from_fn(|a| (gr.x[a] - cv[a]).and(gr.real));
            for c in 0..3 {
                let ag = if UNIT { gs[c] } else { gr.af * gs[c] };
                for e in 0..3 {
                    acc[3 * c + e] = acc[3 * c + e] + ag * r[e];
                }
            }
        });
        if UNIT {
            return;
        }
        over!(acc.mass_r, groups, |acc, gr| {
            let am = gr.af * gr.m;
            let r: [F4; 3] = std::array::from_fn(|a| (gr.x[a] - cv[a]).and(gr.real));
            for c in 0..3 {
                acc[c] = acc[c] + am * cross_at(&r, &gr.v, c);
                acc[3 + c] = acc[3 + c] + am * r[c];
            }
        });
    }

    /// The moments' lanes; with `unit` ([`moment_passes`]), the sums it skipped copied from those they repeat.
    #[inline(always)]
    fn store_moments(acc: &MomentAcc, unit: bool) -> [Lane; q::COUNT] {
        let mut out = [[0.0; VL]; q::COUNT];
        store(&acc.constraints, &mut out[..CONSTRAINT_SUMS]);
        store(&acc.gradient, &mut out[q::FREE_MASS..q::FREE_P]);
        store(&acc.free, &mut out[q::FREE_P..q::A_VV]);
        store(&acc.outer, &mut out[q::A_VV..]);
        if unit {
            out[q::A_FREE_MASS] = out[q::FREE_MASS];
            for a in 0..3 {
                out[q::FREE_P + a] = out[q::MOMENTUM + a];
                out[q::A_FREE_P + a] = out[q::MOMENTUM + a];
                out[q::FREE_L + a] = out[q::ANGULAR + a];
            }
        }
        out
    }

    /// The second-order moments' lanes; with `unit`, the sums [`second_order_passes`] skipped copied from the
    /// moments' lanes `moments`.
    #[inline(always)]
    fn store_second_order(
        acc: &SecondOrderAcc,
        unit: bool,
        moments: &[Lane; q::COUNT],
    ) -> [Lane; SECOND_ORDER_SUMS] {
        let mut out = [[0.0; VL]; SECOND_ORDER_SUMS];
        store(&acc.grad_r, &mut out[..9]);
        store(&acc.mass_r, &mut out[9..]);
        if unit {
            out[9..12].copy_from_slice(&moments[q::ANGULAR..q::ANGULAR + 3]);
            out[12..15].copy_from_slice(&moments[q::FREE_R..q::FREE_R + 3]);
        }
        out
    }

    /// The moments (and, with `SECOND`, the second-order moments) with `UNIT == rows.unit`, each block's
    /// groups loaded once for both; one instance per variant.
    struct Moments<'a, const UNIT: bool, const SECOND: bool> {
        s: V3,
        rows: &'a Rows<'a>,
        g: Vec3,
        center: Vec3,
    }

    impl<const UNIT: bool, const SECOND: bool> Kernel for Moments<'_, UNIT, SECOND> {
        type Output = ([Lane; q::COUNT], Option<[Lane; SECOND_ORDER_SUMS]>);
        #[inline(always)]
        fn call(self) -> Self::Output {
            let Moments { s, rows, g, center } = self;
            let (gv, cv) = (splat3(s, g), splat3(s, center));
            let (mut moments, mut second) = (MomentAcc::zero(s), SecondOrderAcc::zero(s));
            for_blocks(s, rows, |groups| {
                moment_passes::<UNIT>(&mut moments, groups, &gv, &cv);
                if SECOND {
                    second_order_passes::<UNIT>(&mut second, groups, &gv, &cv);
                }
            });
            let moments = store_moments(&moments, UNIT);
            let second = SECOND.then(|| store_second_order(&second, UNIT, &moments));
            (moments, second)
        }
    }

    /// [`super::moment_lanes`] compiled for AVX2 (`s` proves the CPU has it).
    pub(crate) fn moment_lanes(s: V3, rows: &Rows, g: Vec3, center: Vec3) -> [Lane; q::COUNT] {
        rows.assert_lengths();
        let (moments, _) = if rows.unit {
            s.vectorize(Moments::<true, false> { s, rows, g, center })
        } else {
            s.vectorize(Moments::<false, false> { s, rows, g, center })
        };
        moments
    }

    /// [`super::moment_and_second_order_lanes`] compiled for AVX2 (`s` proves the CPU has it).
    pub(crate) fn moment_and_second_order_lanes(
        s: V3,
        rows: &Rows,
        g: Vec3,
        center: Vec3,
    ) -> ([Lane; q::COUNT], [Lane; SECOND_ORDER_SUMS]) {
        rows.assert_lengths();
        let (moments, second) = if rows.unit {
            s.vectorize(Moments::<true, true> { s, rows, g, center })
        } else {
            s.vectorize(Moments::<false, true> { s, rows, g, center })
        };
        (moments, second.expect("asked for"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rows with every kind of value: unequal masses, pinned rows (free mass and factor 0), varied factors,
    /// a gradient that does not cancel gravity.
    fn rows_data(n: usize, seed: u64) -> (Vec<Vec3>, Vec<Vec3>, Vec<Vec3>, [Vec<f64>; 3]) {
        let mut s = seed;
        let mut rnd = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
        };
        let mut vec3 = |scale: f64| [rnd() * scale, rnd() * scale, rnd() * scale];
        let x: Vec<Vec3> = (0..n).map(|_| vec3(2.0)).collect();
        let v: Vec<Vec3> = (0..n).map(|_| vec3(0.5)).collect();
        let grad: Vec<Vec3> = (0..n).map(|_| vec3(30.0)).collect();
        let mass: Vec<f64> = (0..n).map(|i| 0.2 + 0.01 * (i % 17) as f64).collect();
        let pinned = |i: usize| i % 7 == 3;
        let free_mass = (0..n)
            .map(|i| if pinned(i) { 0.0 } else { mass[i] })
            .collect();
        let free_factor = (0..n)
            .map(|i| {
                if pinned(i) {
                    0.0
                } else {
                    1.0 / (1.0 + 0.3 * (i % 5) as f64)
                }
            })
            .collect();
        (x, v, grad, [mass, free_mass, free_factor])
    }

    fn bits<const N: usize>(a: &[Lane; N]) -> Vec<u64> {
        a.iter().flatten().map(|x| x.to_bits()).collect()
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn simd_kernels_match_the_portable_sums_bit_for_bit() {
        let Some(s) = crate::math::simd::V3::try_new() else {
            return;
        };
        let (g, center) = ([0.3, -0.2, -9.81], [0.4, -0.6, 0.5]);
        // Lengths with every tail (0..3 padding lanes), one row, and one to four blocks of 64 rows.
        for n in [1, 4, 5, 6, 7, 8, 61, 64, 65, 130, 255] {
            let (x, v, grad, [mass, free_mass, free_factor]) = rows_data(n, n as u64);
            // With and without the gradient (the warm start's velocity moments need none).
            for grad in [Some(&grad[..]), None] {
                let rows = Rows {
                    x: &x,
                    v: &v,
                    grad,
                    mass: &mass,
                    free_mass: &free_mass,
                    free_factor: &free_factor,
                    unit: false,
                };
                let (c, m, (m2, so)) = (
                    v3::constraint_lanes(s, &x, &v, &mass, g, center),
                    v3::moment_lanes(s, &rows, g, center),
                    v3::moment_and_second_order_lanes(s, &rows, g, center),
                );
                let c_ref = portable::constraint_lanes(&x, &v, &mass, g, center);
                let m_ref = portable::moment_lanes(&rows, g, center);
                let s_ref = portable::second_order_lanes(&rows, g, center);
                assert_eq!(bits(&c), bits(&c_ref), "constraint sums, {n} rows");
                assert_eq!(bits(&m), bits(&m_ref), "moments, {n} rows");
                assert_eq!(
                    bits(&m2),
                    bits(&m_ref),
                    "moments with the second-order ones, {n} rows"
                );
                assert_eq!(bits(&so), bits(&s_ref), "second-order moments, {n} rows");
                // The moments' first sums are the constraint sums.
                assert_eq!(bits(&c_ref), bits(&m_ref)[..VL * CONSTRAINT_SUMS].to_vec());
            }
        }
    }

    /// On rows that are all free with a unit factor, the kernels that skip the repeated sums (`Rows::unit`)
    /// give the bits of the portable sums, which compute every one; the sums they copy are the ones they
    /// repeat. Fails if a skipped sum is not a bit-for-bit repeat, or a factor of one is multiplied where the
    /// reference's order differs.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn unit_rows_skip_the_repeated_sums_and_keep_every_bit() {
        let Some(s) = crate::math::simd::V3::try_new() else {
            return;
        };
        let (g, center) = ([0.3, -0.2, -9.81], [0.4, -0.6, 0.5]);
        for n in [1, 3, 4, 5, 7, 8, 61, 64, 65, 130, 255] {
            let (x, v, grad, [mass, ..]) = rows_data(n, 3 + n as u64);
            let ones = vec![1.0; n];
            for grad in [Some(&grad[..]), None] {
                let plain = Rows {
                    x: &x,
                    v: &v,
                    grad,
                    mass: &mass,
                    free_mass: &mass,
                    free_factor: &ones,
                    unit: false,
                };
                let unit = Rows {
                    unit: true,
                    ..plain
                };
                let (m, (m2, so), m_plain) = (
                    v3::moment_lanes(s, &unit, g, center),
                    v3::moment_and_second_order_lanes(s, &unit, g, center),
                    v3::moment_lanes(s, &plain, g, center),
                );
                let m_ref = portable::moment_lanes(&plain, g, center);
                let s_ref = portable::second_order_lanes(&plain, g, center);
                assert_eq!(bits(&m_plain), bits(&m_ref), "{n} rows");
                assert_eq!(bits(&m), bits(&m_ref), "unit moments, {n} rows");
                assert_eq!(
                    bits(&m2),
                    bits(&m_ref),
                    "unit moments (second pass), {n} rows"
                );
                assert_eq!(
                    bits(&so),
                    bits(&s_ref),
                    "unit second-order moments, {n} rows"
                );
            }
        }
    }

    /// The lanes are sums over the rows: against a plain per-row sum of the same terms (to rounding).
    #[test]
    fn the_sums_are_the_documented_moments() {
        let n = 23;
        let (x, v, grad, [mass, free_mass, free_factor]) = rows_data(n, 7);
        let rows = Rows {
            x: &x,
            v: &v,
            grad: Some(&grad),
            mass: &mass,
            free_mass: &free_mass,
            free_factor: &free_factor,
            unit: false,
        };
        let (g, c) = ([0.3, -0.2, -9.81], [0.4, -0.6, 0.5]);
        let (m, s) = moment_and_second_order_lanes(&rows, g, c);
        let sum = |k: usize| lane_sum(&m[k]);
        let close =
            |a: f64, b: f64| assert!((a - b).abs() <= 1e-12 * (1.0 + b.abs()), "{a} vs {b}");
        let mut want = [0.0; 8];
        let mut want_s = [0.0; 3];
        for i in 0..n {
            let r: Vec3 = std::array::from_fn(|a| x[i][a] - c[a]);
            let gi: Vec3 = std::array::from_fn(|a| grad[i][a] - mass[i] * g[a]);
            let vv = v[i].iter().map(|a| a * a).sum::<f64>();
            want[0] += 0.5 * mass[i] * vv;
            want[1] -= mass[i] * (g[0] * x[i][0] + g[1] * x[i][1] + g[2] * x[i][2]);
            want[2] += mass[i] * (r[1] * v[i][2] - r[2] * v[i][1]);
            want[3] += free_factor[i] * gi.iter().map(|a| a * a).sum::<f64>() / mass[i];
            want[4] += free_mass[i] * vv;
            want[5] += free_factor[i] * mass[i] * v[i][0] * v[i][1];
            want[6] += free_mass[i] * r[2] * r[2];
            want[7] += free_factor[i] * (gi[1] * v[i][2] - gi[2] * v[i][1]);
            want_s[0] += free_factor[i] * gi[0] * r[2];
            want_s[1] += free_factor[i] * mass[i] * (r[0] * v[i][1] - r[1] * v[i][0]);
            want_s[2] += free_factor[i] * mass[i] * r[1];
        }
        close(sum(q::KINETIC), want[0]);
        close(sum(q::GRAVITATIONAL), want[1]);
        close(sum(q::ANGULAR), want[2]);
        close(sum(q::GRAD_SQ_OVER_W), want[3]);
        close(sum(q::TR_VV), want[4]);
        close(sum(q::A_VV + 1), want[5]);
        close(sum(q::RR + 5), want[6]);
        close(sum(q::A_GRAD_CROSS_V), want[7]);
        close(lane_sum(&s[2]), want_s[0]);
        close(lane_sum(&s[11]), want_s[1]);
        close(lane_sum(&s[13]), want_s[2]);
    }
}
