//! Loops compiled for the wider vector instructions of the CPU they run on.
//!
//! The workspace is built for the x86-64 baseline (SSE2: two f64 at a time, and no blend
//! instruction, so a select in a loop becomes a branch per element). faer and gemm choose
//! their kernels when they run; `on_avx2` lets a loop of our own do the same. Only the
//! instructions differ: Rust never fuses a multiply and an add unless asked (`mul_add`), so
//! each element's arithmetic is the same IEEE operations in the same order, the same bits.

/// `fn NAME(args) = KERNEL;` defines `NAME`, which runs the `#[inline(always)]` function
/// `KERNEL` (same arguments, no result) compiled with AVX2 enabled where this CPU has it, as
/// the baseline compiled it elsewhere. The kernel must be inlined into the enabled copy (a
/// call it makes that is not inlined runs as the baseline compiled it): a closure handed to a
/// generic wrapper was not, once it held a few loops.
macro_rules! on_avx2 {
    ($(#[$doc:meta])* fn $name:ident($($arg:ident: $ty:ty),* $(,)?) = $kernel:path;) => {
        $(#[$doc])*
        fn $name($($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") {
                /// # Safety
                /// Only on a CPU with AVX2.
                #[target_feature(enable = "avx2")]
                unsafe fn enabled($($arg: $ty),*) {
                    $kernel($($arg),*)
                }
                // SAFETY: the CPU has AVX2, asked just above.
                return unsafe { enabled($($arg),*) };
            }
            $kernel($($arg),*)
        }
    };
}
pub(crate) use on_avx2;
