/* Which x86 SIMD code this build and this CPU can run: shared by the AVX-512 kernels of both extensions
 * (radiometry/_ckernels_simd.h, mapping/_ckernels_raycast_simd.h).
 *
 * RM_NO_SIMD (-DRM_NO_SIMD) builds without them, as do compilers other than GCC >= 8 / Clang >= 6 (the first with
 * GFNI's intrinsics and target name) and other architectures: then RM_X86_SIMD is 0 and an older compiler does not
 * fail the whole extension. */
#ifndef RADIOMAP_SIMD_CPU_H
#define RADIOMAP_SIMD_CPU_H

#if defined(__clang__)
#define RM_COMPILER_OK (__clang_major__ >= 6)
#elif defined(__GNUC__)
#define RM_COMPILER_OK (__GNUC__ >= 8)
#else
#define RM_COMPILER_OK 0
#endif

#if !defined(RM_NO_SIMD) && RM_COMPILER_OK && (defined(__x86_64__) || defined(__i386__))
#define RM_X86_SIMD 1
#include <cpuid.h>
#include <immintrin.h>

/* whether this CPU (and the OS, which must save the 512-bit registers) has the AVX-512 features whose CPUID leaf 7
 * bits are ``ebx`` and ``ecx``; XGETBV for the saved state (read directly rather than with __builtin_cpu_supports,
 * whose feature names older compilers do not know). CPUID traps to the hypervisor on virtual machines: callers
 * cache the answer. */
static inline int rm_cpu_avx512(unsigned int ebx, unsigned int ecx)
{
    unsigned int a, b, c, d;
    if (!__get_cpuid(1, &a, &b, &c, &d) || !(c & (1u << 27))) /* OSXSAVE */
        return 0;
    unsigned int lo, hi;
    __asm__ volatile("xgetbv" : "=a"(lo), "=d"(hi) : "c"(0));
    if ((lo & 0xe6) != 0xe6) /* XMM, YMM, opmask, ZMM 0-15 and 16-31 state */
        return 0;
    if (!__get_cpuid_count(7, 0, &a, &b, &c, &d))
        return 0;
    return (b & ebx) == ebx && (c & ecx) == ecx;
}

/* defines ``static int NAME(void)``: rm_cpu_avx512(EBX, ECX), detected once (a race writes the same value) */
#define RM_CPU_CHECK(NAME, EBX, ECX)                                                                               \
    static int NAME(void)                                                                                          \
    {                                                                                                              \
        static int cached = -1;                                                                                    \
        if (cached < 0)                                                                                            \
            cached = rm_cpu_avx512((EBX), (ECX));                                                                  \
        return cached;                                                                                             \
    }
#else
#define RM_X86_SIMD 0
#endif

#endif
