//! Run-time SIMD dispatch. The kernels are written once, as portable code on fixed-width lane arrays or on
//! `pulp`'s lane types, and compiled a second time with the AVX2 features (pulp's [`V3`]: AVX2, FMA, BMI)
//! for CPUs that have them; which one runs is decided at run time. Both builds run the same operations in
//! the same order: the compiler never fuses a multiplication and an addition by itself (Rust does not
//! allow floating-point contraction), and the kernels call no fused multiply-add, so every build gives the
//! same bits.
//!
//! The one `unsafe` block of this module is [`run_avx512`]'s call of a function compiled for AVX-512F,
//! which `pulp` exposes only behind a feature that would also switch faer's own kernels (and their bits).

#[cfg(target_arch = "x86_64")]
pub(crate) use pulp::x86::V3;
pub(crate) use pulp::NullaryFnOnce as Kernel;

/// Runs `k` compiled for AVX2 + FMA where the CPU has them, else as compiled for the target. `k.call`
/// must be `#[inline(always)]` and call only `#[inline(always)]` code for the features to reach it.
#[inline(always)]
pub(crate) fn run_avx2<K: Kernel>(k: K) -> K::Output {
    #[cfg(target_arch = "x86_64")]
    if let Some(simd) = V3::try_new() {
        return simd.vectorize(k);
    }
    k.call()
}

/// Runs `k` compiled for AVX-512F where the CPU has it (`Ok`), else hands it back (`Err`). As in
/// [`run_avx2`], `k.call` must be inlined whole.
#[inline(always)]
pub(crate) fn run_avx512<K: Kernel>(k: K) -> Result<K::Output, K> {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx512f") {
        #[target_feature(enable = "avx512f")]
        #[inline]
        fn avx512<K: Kernel>(k: K) -> K::Output {
            k.call()
        }
        // SAFETY: the CPU supports AVX-512F (checked above), the only requirement of a safe function with
        // target features.
        return Ok(unsafe { avx512(k) });
    }
    Err(k)
}

/// Defines `fn $name<'a>(args) -> R` that runs `$body(args)` (an `#[inline(always)]` function) compiled
/// for AVX2 where the CPU has it ([`run_avx2`]). Every reference among the arguments names the lifetime
/// `'a`. A rayon task should call such a function: code in a closure does not inherit the target features
/// of the function that creates it.
macro_rules! avx2_dispatch {
    ($(#[$m:meta])* $vis:vis fn $name:ident<$lt:lifetime>($($arg:ident: $ty:ty),* $(,)?) $(-> $ret:ty)? => $body:path) => {
        $(#[$m])*
        $vis fn $name<$lt>($($arg: $ty),*) $(-> $ret)? {
            struct Op<$lt> {
                $($arg: $ty),*
            }
            impl<$lt> $crate::math::simd::Kernel for Op<$lt> {
                type Output = avx2_dispatch!(@ret $($ret)?);
                #[inline(always)]
                fn call(self) -> Self::Output {
                    let Op { $($arg),* } = self;
                    $body($($arg),*)
                }
            }
            $crate::math::simd::run_avx2(Op { $($arg),* })
        }
    };
    (@ret) => { () };
    (@ret $ret:ty) => { $ret };
}
pub(crate) use avx2_dispatch;

#[cfg(target_arch = "x86_64")]
pub(crate) use lanes4::F4;

/// Four `f64` lanes in an AVX register, with the token that proves the CPU has AVX2 (a value can only be
/// made from a [`V3`]), so the operators compile to single AVX instructions in safe code. The lanes are kept
/// as the register type (not as `pulp::f64x4`, an array of four scalars that the optimiser splits into
/// scalar values across loops).
#[cfg(target_arch = "x86_64")]
mod lanes4 {
    use super::V3;
    use core::arch::x86_64::{__m256d, _CMP_GT_OQ};
    use pulp::{cast, u64x4};
    use std::ops::{Add, Div, Mul, Neg, Sub};

    #[derive(Clone, Copy)]
    pub(crate) struct F4 {
        simd: V3,
        v: __m256d,
    }

    impl F4 {
        #[inline(always)]
        fn with(self, v: __m256d) -> Self {
            Self { simd: self.simd, v }
        }

        /// The token this value was made with.
        #[inline(always)]
        pub(crate) fn simd(self) -> V3 {
            self.simd
        }

        #[inline(always)]
        pub(crate) fn splat(simd: V3, value: f64) -> Self {
            Self {
                simd,
                v: simd.avx._mm256_set1_pd(value),
            }
        }

        #[inline(always)]
        pub(crate) fn zero(simd: V3) -> Self {
            Self {
                simd,
                v: simd.avx._mm256_setzero_pd(),
            }
        }

        #[inline(always)]
        pub(crate) fn from_array(simd: V3, values: [f64; 4]) -> Self {
            Self {
                simd,
                v: cast(values),
            }
        }

        #[inline(always)]
        pub(crate) fn to_array(self) -> [f64; 4] {
            cast(self.v)
        }

        /// All bits set on the lanes where `flags` is false, clear where it is true (a mask for [`F4::and`]
        /// and [`F4::select`]).
        #[inline(always)]
        pub(crate) fn mask_unless(simd: V3, flags: [bool; 4]) -> Self {
            let f = u64x4(
                u64::from(flags[0]),
                u64::from(flags[1]),
                u64::from(flags[2]),
                u64::from(flags[3]),
            );
            let m = simd.cmp_eq_u64x4(f, simd.splat_u64x4(0));
            Self { simd, v: cast(m) }
        }

        /// All bits set on every lane.
        #[inline(always)]
        pub(crate) fn all_bits(simd: V3) -> Self {
            Self::splat(simd, f64::from_bits(u64::MAX))
        }

        /// The bits of `self` where `mask`'s are set.
        #[inline(always)]
        pub(crate) fn and(self, mask: Self) -> Self {
            self.with(self.simd.avx._mm256_and_pd(self.v, mask.v))
        }

        /// `if_true` on the lanes whose `self` has the sign bit set (an all-bits mask), else `if_false`.
        #[inline(always)]
        pub(crate) fn select(self, if_true: Self, if_false: Self) -> Self {
            self.with(
                self.simd
                    .avx
                    ._mm256_blendv_pd(if_false.v, if_true.v, self.v),
            )
        }

        /// A mask of the lanes where `self > 0` (ordered: false on NaN).
        #[inline(always)]
        pub(crate) fn positive(self) -> Self {
            let avx = self.simd.avx;
            self.with(avx._mm256_cmp_pd::<_CMP_GT_OQ>(self.v, avx._mm256_setzero_pd()))
        }

        /// Four rows of three values (`x0 y0 z0 x1 ...`) as three lane vectors (x, y, z).
        #[inline(always)]
        pub(crate) fn rows3(simd: V3, p: &[f64; 12]) -> [Self; 3] {
            let avx = simd.avx;
            let ld = |k: usize| -> __m256d { cast([p[k], p[k + 1], p[k + 2], p[k + 3]]) };
            let (a, b, c) = (ld(0), ld(4), ld(8)); // x0 y0 z0 x1 | y1 z1 x2 y2 | z2 x3 y3 z3
            let lo_a_hi_c = avx._mm256_permute2f128_pd::<0x30>(a, c); // x0 y0 y3 z3
            let hi_a_lo_c = avx._mm256_permute2f128_pd::<0x21>(a, c); // z0 x1 z2 x3
            let x = avx._mm256_shuffle_pd::<0b1010>(
                avx._mm256_blend_pd::<0b0100>(lo_a_hi_c, b),
                hi_a_lo_c,
            );
            let y = avx._mm256_permute_pd::<0b0101>(avx._mm256_blend_pd::<0b1001>(lo_a_hi_c, b));
            let z = avx
                ._mm256_blend_pd::<0b1000>(avx._mm256_blend_pd::<0b0010>(hi_a_lo_c, b), lo_a_hi_c);
            [x, y, z].map(|v| Self { simd, v })
        }

        /// The inverse of [`F4::rows3`].
        #[inline(always)]
        pub(crate) fn to_rows3([x, y, z]: [Self; 3]) -> [f64; 12] {
            let avx = x.simd.avx;
            let (x, y, z) = (x.v, y.v, z.v);
            let xy = avx._mm256_unpacklo_pd(x, y); // x0 y0 x2 y2
            let zx = avx._mm256_shuffle_pd::<0b1010>(z, x); // z0 x1 z2 x3
            let yz = avx._mm256_shuffle_pd::<0b1111>(y, z); // y1 z1 y3 z3
            let a = avx._mm256_permute2f128_pd::<0x20>(xy, zx); // x0 y0 z0 x1
            let b = avx._mm256_blend_pd::<0b1100>(yz, xy); // y1 z1 x2 y2
            let c = avx._mm256_permute2f128_pd::<0x31>(zx, yz); // z2 x3 y3 z3
            cast([a, b, c])
        }
    }

    macro_rules! binop {
        ($trait:ident, $method:ident, $op:ident) => {
            impl $trait for F4 {
                type Output = F4;
                #[inline(always)]
                fn $method(self, rhs: F4) -> F4 {
                    self.with(self.simd.avx.$op(self.v, rhs.v))
                }
            }
        };
    }
    binop!(Add, add, _mm256_add_pd);
    binop!(Sub, sub, _mm256_sub_pd);
    binop!(Mul, mul, _mm256_mul_pd);
    binop!(Div, div, _mm256_div_pd);

    impl Neg for F4 {
        type Output = F4;
        /// A sign flip (as the scalar negation: `-(+0) = -0`).
        #[inline(always)]
        fn neg(self) -> F4 {
            let avx = self.simd.avx;
            self.with(avx._mm256_xor_pd(self.v, avx._mm256_set1_pd(-0.0)))
        }
    }
}
