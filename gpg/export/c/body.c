
#define N_LEVELS (N_OUT - 6)

#if HAS_BINS
/* the query's bin (gpg.gp.partition.Partition.lookup): a value on a split goes left */
static int lookup(const double xn[D_IN]) {
#if SLAB
  int b = 0, i;
  for (i = 0; i < N_CUTS; i++) b += xn[SPLIT_DIM[0]] > SPLIT_VALUE[i];
  return b;
#else
  int node = 0;
  if (N_BINS == 1) return 0;
  while (node >= 0) node = xn[SPLIT_DIM[node]] <= SPLIT_VALUE[node] ? LEFT[node] : RIGHT[node];
  return -node - 1;
#endif
}

/* k(x, X_p) for n points, then one block of gradient rows k (x_a - X_pa) / l_a^2 per
 * gradient dimension a (gpg.gp.kernels.query_rows) */
HOT static void krows(const double xn[D_IN], const real *X, int n, real *out) {
  int p, i, g, a;
  double r2, t, k;
  for (p = 0; p < n; p++) {
    r2 = 0.0;
    for (i = 0; i < D_IN; i++) {
      t = (xn[i] - (double)X[p * D_IN + i]) / LENGTHSCALE[i];
      r2 += t * t;
    }
    k = SIGMA_NOISE[0] * exp(-0.5 * r2);
    out[p] = (real)k;
    for (g = 0; g < N_GRAD; g++) {
      a = GRAD_DIMS[g];
      out[(1 + g) * n + p] = (real)(k * (xn[a] - (double)X[p * D_IN + a]) /
                                    (LENGTHSCALE[a] * LENGTHSCALE[a]));
    }
  }
}

/* the kernel row of bin b's near set (shared rows first); returns its length R_b */
static int kernel_row(const double xn[D_IN], int b, real *k) {
  int u = N_SHARED * (1 + N_GRAD);
  if (N_SHARED) krows(xn, SHARED, N_SHARED, k);
  krows(xn, PTS + BIN_PT_OFF[b] * D_IN, BIN_NPTS[b], k + u);
  return u + BIN_NPTS[b] * (1 + N_GRAD);
}
#endif

#if HAS_VAR
/* sigma - |F_b k|^2, F_b row by row (each row's non-zero span, contiguous): a dot product
 * per row whose four partial sums stay in registers (the column-by-column axpy it replaces
 * was bound by its stores, one sum by its additions' latency). With GCC or clang the sums are
 * vectors: 32 bytes (AVX2), and 64 bytes in a version for CPUs with AVX-512, picked at run
 * time (64-byte vectors split in two on AVX2 were 3x slower). -DGPG_NO_VECTOR, or another
 * compiler, takes the scalar loop. */
#if (defined(__clang__) || (defined(__GNUC__) && __GNUC__ >= 9)) && !defined(GPG_NO_VECTOR)
#if FREAL_IS_REAL
#define VLOAD(V, T, F) memcpy(&(V), (F), sizeof(V))
#else
#define VLOAD(V, T, F) \
  do { T##_f t_; memcpy(&t_, (F), sizeof t_); (V) = __builtin_convertvector(t_, T); } while (0)
#endif
#define ROW_DOT(NAME, T, W)                                                                  \
  static inline real NAME(const freal *f, const real *k, int len) {                         \
    T a = {0}, b = {0}, c = {0}, d = {0}, kv, fv;                                            \
    real s = 0;                                                                              \
    int i, j;                                                                                \
    for (i = 0; i + 4 * (W) <= len; i += 4 * (W)) {                                          \
      memcpy(&kv, k + i, sizeof kv); VLOAD(fv, T, f + i); a += fv * kv;                      \
      memcpy(&kv, k + i + (W), sizeof kv); VLOAD(fv, T, f + i + (W)); b += fv * kv;          \
      memcpy(&kv, k + i + 2 * (W), sizeof kv); VLOAD(fv, T, f + i + 2 * (W)); c += fv * kv;  \
      memcpy(&kv, k + i + 3 * (W), sizeof kv); VLOAD(fv, T, f + i + 3 * (W)); d += fv * kv;  \
    }                                                                                        \
    for (; i + (W) <= len; i += (W)) {                                                       \
      memcpy(&kv, k + i, sizeof kv); VLOAD(fv, T, f + i); a += fv * kv;                      \
    }                                                                                        \
    a += b; c += d; a += c;                                                                  \
    for (j = 0; j < (W); j++) s += a[j];                                                     \
    for (; i < len; i++) s += (real)f[i] * k[i];                                             \
    return s;                                                                                \
  }
typedef real v32 __attribute__((vector_size(32)));
typedef freal v32_f __attribute__((vector_size(32 / sizeof(real) * sizeof(freal))));
ROW_DOT(row_dot, v32, (int)(32 / sizeof(real)))
#else
static real row_dot(const freal *f, const real *k, int len) {
  real s0 = 0, s1 = 0, s2 = 0, s3 = 0;
  int i;
  for (i = 0; i + 3 < len; i += 4) {
    s0 += (real)f[i] * k[i]; s1 += (real)f[i + 1] * k[i + 1];
    s2 += (real)f[i + 2] * k[i + 2]; s3 += (real)f[i + 3] * k[i + 3];
  }
  for (; i < len; i++) s0 += (real)f[i] * k[i];
  return (s0 + s1) + (s2 + s3);
}
#endif

#define LATENT_VARIANCE(NAME, DOT)                                                           \
  static double NAME(const real *k, int b, int nr) {                                        \
    double q = 0.0, v;                                                                       \
    long base = ROW_BASE[b];                                                                 \
    int r;                                                                                   \
    for (r = 0; r < nr; r++) {                                                               \
      v = (double)DOT(FACT + ROW_OFF[base + r], k + ROW_FIRST[base + r], ROW_LEN[base + r]); \
      q += v * v;                                                                            \
    }                                                                                        \
    return SIGMA_NOISE[0] - q;                                                               \
  }
HOT LATENT_VARIANCE(latent_variance_any, row_dot)

#if defined(GPG_CLONES) && !defined(GPG_NO_AVX512) && !defined(GPG_NO_VECTOR)
#pragma GCC push_options
#pragma GCC target("arch=x86-64-v4")
typedef real v64 __attribute__((vector_size(64)));
typedef freal v64_f __attribute__((vector_size(64 / sizeof(real) * sizeof(freal))));
ROW_DOT(row_dot64, v64, (int)(64 / sizeof(real)))
LATENT_VARIANCE(latent_variance64, row_dot64)
#pragma GCC pop_options
#define HAS_AVX512()                                                                         \
  (__builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512vl") &&               \
   __builtin_cpu_supports("avx512bw") && __builtin_cpu_supports("avx512dq"))
#else
#define HAS_AVX512() 0
#define latent_variance64 latent_variance_any
#endif

static double latent_variance(const real *k, int b, int nr) {
  return HAS_AVX512() ? latent_variance64(k, b, nr) : latent_variance_any(k, b, nr);
}
#endif

#if HAS_GLOBAL_MEAN || HAS_CORR
/* exp(x) for x <= 0 without a branch or a call, so that the loop over the training points
 * vectorises: x = n ln2 + r with |r| <= ln2/2 (n rounded to nearest by adding 1.5 * 2^52),
 * exp(r) by its Taylor polynomial of degree 13 (truncation below 1e-17 relative), 2^n written
 * into the exponent's bits; 0 below -708, where exp leaves the normal doubles (a select by
 * bit masks from the sign of x + 708: a comparison would be a branch at -O2) */
static inline double vexp(double x) {
  const double shift = 6755399441055744.0, lowest = -708.0;
  double y = x + 708.0, t, n, r, p, s;
  unsigned long long bits, keep, xb, lb;
  memcpy(&keep, &y, sizeof keep);
  keep = ~(unsigned long long)((long long)keep >> 63);
  memcpy(&xb, &x, sizeof xb);
  memcpy(&lb, &lowest, sizeof lb);
  xb = (xb & keep) | (lb & ~keep);
  memcpy(&y, &xb, sizeof y);
  t = y * 1.4426950408889634 + shift;
  n = t - shift;
  r = (y - n * 0.693147180369123816490) - n * 1.90821492927058770002e-10;
  {
    /* its even and odd terms as two chains in r^2, half as long as one (the loop's cost is
     * the chain's latency: docs/measurements.md, the C mean where only AVX2 runs) */
    double r2 = r * r, pe, po;
    pe = 2.08767569878680989792e-09;
    pe = pe * r2 + 2.75573192239858906526e-07;
    pe = pe * r2 + 2.48015873015873015873e-05;
    pe = pe * r2 + 1.38888888888888888889e-03;
    pe = pe * r2 + 4.16666666666666666667e-02;
    pe = pe * r2 + 0.5;
    pe = pe * r2 + 1.0;
    po = 1.6059043836821613e-10;
    po = po * r2 + 2.50521083854417187751e-08;
    po = po * r2 + 2.75573192239858906526e-06;
    po = po * r2 + 1.98412698412698412698e-04;
    po = po * r2 + 8.33333333333333333333e-03;
    po = po * r2 + 1.66666666666666666667e-01;
    po = po * r2 + 1.0;
    p = pe + r * po;
  }
  memcpy(&bits, &t, sizeof bits);
  bits = (bits - 0x4338000000000000ULL + 1023ULL) << 52;
  memcpy(&s, &bits, sizeof s);
  p = p * s;
  memcpy(&bits, &p, sizeof bits);
  bits &= keep;
  memcpy(&p, &bits, sizeof p);
  return p;
}
#endif

#if HAS_GLOBAL_MEAN
/* the folded exact mean of gpg.gp.mean (normalised units): sum_p k(x, x_p) c_p, in two
 * passes over the points: the kernel values (the squared distance over the D_IN inputs and
 * its exp, one loop over the points that GCC vectorises across them, the distances never
 * stored), then the coefficients' sums held in registers (coef_sums). (The unfolded sum of
 * gpg.export.layout's alpha was tried: no more accurate in float here, where the
 * coefficients' own rounding dominates, and half again slower.) */
HOT_MEAN FUSED static void global_mean(const double xn[D_IN], double yn[N_OUT]) {
  double k[N_MEAN], acc[N_OUT * (1 + N_GRAD)], xl[D_IN];
  int i, j, p;
  for (i = 0; i < D_IN; i++) xl[i] = xn[i] * INV_LS_M[i];
  for (p = 0; p < N_MEAN; p++) {
    /* four partial sums: four short chains of multiply-adds, not one long one */
    double ra = 0.0, rb = 0.0, rc = 0.0, rd = 0.0, t;
    for (i = 0; i + 3 < D_IN; i += 4) {
      t = xl[i] - XS_T[(long)i * N_MEAN + p]; ra += t * t;
      t = xl[i + 1] - XS_T[(long)(i + 1) * N_MEAN + p]; rb += t * t;
      t = xl[i + 2] - XS_T[(long)(i + 2) * N_MEAN + p]; rc += t * t;
      t = xl[i + 3] - XS_T[(long)(i + 3) * N_MEAN + p]; rd += t * t;
    }
    for (; i < D_IN; i++) { t = xl[i] - XS_T[(long)i * N_MEAN + p]; ra += t * t; }
    k[p] = vexp(-0.5 * ((ra + rb) + (rc + rd)));
  }
  coef_sums(k, acc);
  for (j = 0; j < N_OUT; j++) {
    double mu = acc[j];
    for (i = 0; i < N_GRAD; i++) {
      int a = GRAD_DIMS[i];
      mu += xn[a] * INV_LS_M[a] * INV_LS_M[a] * acc[(1 + i) * N_OUT + j];
    }
    yn[j] = SIGMA_M[0] * mu;
  }
}
#endif

/*@CORRECTION@*/

/* the GP's input x (physical units) and R_WH of a world-frame state; eg the attitude the GP
 * reads it at (the half-turn image's, HALF_TURN, where the airflow comes from behind) */
static void gp_input(const double rpm[4], const double euler[3], const double v_air[3],
                     double x[D_IN], double rwh[3][3], double eg[3]) {
  int i;
  for (i = 0; i < 4; i++) x[i] = rpm[i];
  for (i = 0; i < 3; i++) eg[i] = euler[i];
#if BODY_FRAME
  /* the GP's frame is the body's: x = (rpm, R_WB^T v_air) */
  rot_wb(euler[0], euler[1], euler[2], rwh);
  for (i = 0; i < 3; i++)
    x[4 + i] = rwh[0][i] * v_air[0] + rwh[1][i] * v_air[1] + rwh[2][i] * v_air[2];
#else
  {
    double eh[3];
    to_airflow(euler, v_air, eh, rwh);
#if HALF_TURN
    if (cos(eh[0]) < 0.0) { /* the body turned half a turn about z, r1 <-> r3 and r2 <-> r4 */
      eg[0] = euler[0] + 3.141592653589793; eg[1] = -euler[1]; eg[2] = -euler[2];
      for (i = 0; i < 4; i++) x[i] = rpm[(i + 2) % 4];
      to_airflow(eg, v_air, eh, rwh);
    }
#endif
    for (i = 0; i < 3; i++) x[4 + i] = eh[i];
    x[7] = norm3(v_air);
  }
#endif
}

#if HAS_ONLINE
#define ONLINE_ARG , const ONLINE_T *st
#define ONLINE_PASS(S) , S
#else
#define ONLINE_ARG
#define ONLINE_PASS(S)
#endif

#if !HAS_GLOBAL_MEAN
/* the binned mean: bin b's coefficients times its kernel row k (filled here; its length) */
static int binned_mean(const double xn[D_IN], int b, real *k, double yn[N_OUT]) {
  int i, j, nr = kernel_row(xn, b, k);
  for (j = 0; j < N_OUT; j++) {
    const real *c = BCOEF + BCOEF_OFF[b] + (long)j * nr;
    double s = 0.0;
    for (i = 0; i < nr; i++) s += (double)c[i] * (double)k[i];
    yn[j] = s;
  }
  return nr;
}
#endif

static int evaluate(const double rpm[4], const double euler[3], const double v_air[3],
                    double force[3], double torque[3], double *levels,
                    double *variance ONLINE_ARG) {
  double rwh[3][3], x[D_IN], xn[D_IN], yn[N_OUT], y[N_OUT], eg[3], span, tol, latent = 0.0;
  int i, j, b = 0, nr = 0, in_domain = 1;
#if HAS_BINS
  real k[MAX_ROWS];
#endif
#if HAS_CORR
  double pvn[N_OUT];
#endif
  for (i = 0; i < 3; i++) { force[i] = 0.0; torque[i] = 0.0; }
  for (i = 0; i < N_LEVELS; i++) levels[i] = 0.0;
  if (variance) for (i = 0; i < N_OUT; i++) variance[i] = 0.0;
  for (i = 0; i < 4; i++) if (!isfinite(rpm[i])) return 0;
  for (i = 0; i < 3; i++) if (!isfinite(euler[i]) || !isfinite(v_air[i])) return 0;
  gp_input(rpm, euler, v_air, x, rwh, eg);
#if BODY_FRAME
  /* in domain inside the ball */
  if (x[4] * x[4] + x[5] * x[5] + x[6] * x[6] >
      (BALL_RADIUS * (1.0 + 1e-9)) * (BALL_RADIUS * (1.0 + 1e-9)))
    in_domain = 0;
#endif
  for (i = 0; i < N_BOX; i++) {
    span = BOX_HI[i] - BOX_LO[i];
    tol = 1e-9 * (span > 1.0 ? span : 1.0);
    if (x[i] < BOX_LO[i] - tol || x[i] > BOX_HI[i] + tol) in_domain = 0;
  }
  for (i = 0; i < 4; i++) if (rpm[i] < 0.0) in_domain = 0;
#if !BODY_FRAME
  if (in_domain && !(frame_rate(eg, v_air) <= MAX_FRAME_RATE)) in_domain = 0;
#endif
  for (i = 0; i < D_IN; i++) xn[i] = (x[i] - X_LO[i]) / HALF[i] - 1.0;
#if HAS_BINS
  b = lookup(xn);
#endif
#if HAS_GLOBAL_MEAN
  global_mean(xn, yn);
#else
  nr = binned_mean(xn, b, k, yn);
#endif
#if HAS_VAR
  if (variance) {
    if (!nr) nr = kernel_row(xn, b, k);
    latent = latent_variance(k, b, nr);
  }
#endif
  (void)b; (void)nr; (void)latent;
#if HAS_TRACKER
  double prior[N_OUT]; /* the tracked columns read the prior's mean */
  double dl[6] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0}; /* each delta's latent variance, its scale */
  for (j = 0; j < N_OUT; j++) prior[j] = yn[j];
#endif
#if HAS_CORR
#if HAS_TRACKER
  corrected(x, xn, yn, latent, variance ? pvn : 0, variance ? dl : 0);
#else
  corrected(x, xn, yn, latent, variance ? pvn : 0, 0);
#endif
#endif
#if HAS_TRACKER
  if (st) tracker_eta(st, x, prior, yn, variance ? pvn : 0, dl);
#elif HAS_ONLINE
  if (st) online_eta(st, xn, yn, variance ? pvn : 0);
#endif
  for (j = 0; j < N_OUT; j++) y[j] = yn[j] * Y_STD[j] + Y_MEAN[j];
  for (i = 0; i < 3; i++)
    for (j = 0; j < 3; j++) { force[i] += rwh[i][j] * y[j]; torque[i] += rwh[i][j] * y[3 + j]; }
  for (i = 0; i < N_LEVELS; i++) levels[i] = y[6 + i];
#if HAS_ALLOCATION
  /* M at the world attitude: A r^2 = (sum T, tau_x, tau_y, tau_z), thrust along -z_B */
  {
    double u[4] = {0.0, 0.0, 0.0, 0.0}, fb[3], rwb[3][3];
    for (i = 0; i < 4; i++)
      for (j = 0; j < 4; j++) u[i] += ALLOCATION[i * 4 + j] * rpm[j] * rpm[j];
    fb[0] = 0.0; fb[1] = 0.0; fb[2] = -u[0];
    rot_wb(euler[0], euler[1], euler[2], rwb);
    for (i = 0; i < 3; i++)
      for (j = 0; j < 3; j++) { force[i] += rwb[i][j] * fb[j]; torque[i] += rwb[i][j] * u[1 + j]; }
  }
#endif
  if (variance) {
    /* c_m (latent + nu^2) std_m^2 per output in H, then diag(R diag(d) R^T) for the vectors */
    double pv[N_OUT];
#if HAS_CORR
    for (j = 0; j < N_OUT; j++) pv[j] = pvn[j] * Y_STD[j] * Y_STD[j];
#else
    for (j = 0; j < N_OUT; j++)
      pv[j] = OUTPUT_SCALE[j] * ((latent > 0.0 ? latent : 0.0) + SIGMA_NOISE[1]) * Y_STD[j] *
              Y_STD[j];
#endif
    for (i = 0; i < 3; i++) {
      variance[i] = 0.0; variance[3 + i] = 0.0;
      for (j = 0; j < 3; j++) {
        variance[i] += rwh[i][j] * rwh[i][j] * pv[j];
        variance[3 + i] += rwh[i][j] * rwh[i][j] * pv[3 + j];
      }
    }
    for (i = 6; i < N_OUT; i++) variance[i] = pv[i];
    for (i = 0; i < N_OUT; i++) if (!isfinite(variance[i])) in_domain = 0;
  }
  for (i = 0; i < 3; i++) if (!isfinite(force[i]) || !isfinite(torque[i])) in_domain = 0;
  for (i = 0; i < N_LEVELS; i++) if (!isfinite(levels[i])) in_domain = 0;
  return in_domain;
}
