#if defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 11 && \
    defined(__x86_64__) && defined(__linux__) && defined(__GLIBC__) && !defined(GPG_NO_CLONES)
#define GPG_CLONES 1
#define HOT __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define HOT
#endif


/* the mean's multiply-adds fused where the CPU has them (GCC leaves them apart under -std=c99):
 * one rounding instead of two, and half the instructions, in the AVX2 clone */
#if defined(__GNUC__) && !defined(__clang__)
#define FUSED __attribute__((optimize("fp-contract=fast")))
#else
#define FUSED
#endif
