#if defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 11 && \
    defined(__x86_64__) && defined(__linux__) && defined(__GLIBC__) && !defined(GPG_NO_CLONES)
#define GPG_CLONES 1
#define HOT __attribute__((target_clones("arch=x86-64-v3", "default")))
#if defined(GPG_NO_AVX512)
#define HOT_MEAN HOT
#else
#define HOT_MEAN __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#endif
#else
#define HOT
#define HOT_MEAN
#endif


/* the hot loops' multiply-adds fused where the CPU has them (GCC leaves them apart under
 * -std=c99): one rounding instead of two, and half the instructions, in the AVX2 clone; and
 * vectorised where a loop's count or its pointers' overlap is known only at run time (the
 * cost model of -O2 leaves those loops scalar) */
#if defined(__GNUC__) && !defined(__clang__)
#define FUSED __attribute__((optimize("fp-contract=fast", "vect-cost-model=dynamic")))
#else
#define FUSED
#endif
