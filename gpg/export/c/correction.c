
/* A model corrected by flights (gpg.flight.correction.Corrected, gpg.export.layout.Correction):
 * per load output j, in the GP's frame and normalised units, the mean
 *   rho_j mu_j + kappa_j m_j(x) + sum_t beta_jt h_jt(x) + delta_j(xn)
 * and the predictive variance
 *   rho_j^2 c_j max(v, 0) + c_dj (max(sigma_j - |T_j k|^2, 0) + nu_j^2)
 *   + |C_j^T (hbar_j - G_j^T k)|^2,
 * |T_j k|^2 = |W_j k|^2 - |P_j k|^2 (gpg.export.layout.Discrepancy.variance_factor: one
 * triangle where an inducing-point discrepancy has two),
 * with m_j M's loads, h_j the physical columns (gpg.flight.basis.PhysicalBasis) and hbar_j the
 * integrated columns (the prior's mean, m_j, then h_j). Everything here is double (the
 * physics cancels in float), but for the triangles T_j in a float export: the largest arrays,
 * read whole at every query, stored in float (treal) and summed in double. */

#if HAS_KAPPA
/* M's loads in the GP's frame (gpg.flight.correction.SimpleBasis), normalised */
static void simple_columns(const double x[D_IN], double out[6]) {
  double u[4] = {0.0, 0.0, 0.0, 0.0}, f[3], t[3], R[3][3];
  int i, j;
  for (i = 0; i < 4; i++)
    for (j = 0; j < 4; j++) u[i] += CORR_ALLOCATION[i * 4 + j] * x[j] * x[j];
  f[0] = 0.0; f[1] = 0.0; f[2] = -u[0];
  t[0] = u[1]; t[1] = u[2]; t[2] = u[3];
#if BODY_FRAME
  for (i = 0; i < 3; i++) { out[i] = f[i]; out[3 + i] = t[i]; }
#else
  rot_wb(x[4], x[5], x[6], R);
  for (i = 0; i < 3; i++) {
    out[i] = 0.0; out[3 + i] = 0.0;
    for (j = 0; j < 3; j++) { out[i] += R[i][j] * f[j]; out[3 + i] += R[i][j] * t[j]; }
  }
#endif
  for (i = 0; i < 6; i++) out[i] /= Y_STD[i];
  (void)R;
}
#endif

#if N_TERMS
/* the physical columns h[6][N_TERMS] (gpg.flight.basis.PhysicalBasis, TERMS' order), normalised */
static void physical_columns(const double x[D_IN], double h[6][N_TERMS]) {
  double R[3][3], vb[3], speed, w[4], f[4][3], col[6], e2 = 0.0;
  int i, a, t, term;
#if BODY_FRAME
  for (i = 0; i < 3; i++) {
    vb[i] = x[4 + i];
    for (a = 0; a < 3; a++) R[i][a] = i == a;
  }
#else
  rot_wb(x[4], x[5], x[6], R);
  for (i = 0; i < 3; i++) vb[i] = R[0][i] * x[7];
#endif
  speed = sqrt(vb[0] * vb[0] + vb[1] * vb[1] + vb[2] * vb[2] + 1e-12);
  for (i = 0; i < 4; i++) w[i] = x[i] / CORR_RPM_REF;
  e2 = vb[0] * vb[0] + vb[1] * vb[1];
  for (t = 0; t < N_TERMS; t++) {
    for (i = 0; i < 6; i++) col[i] = 0.0;
    if (t < 3) { /* airframe drag along body axis t */
      col[t] = -0.5 * CORR_AIR_DENSITY * speed * vb[t];
    } else {
      term = t - 3; /* 0: rotor drag, 1: inflow, 2: edgewise */
      for (i = 0; i < 4; i++) {
        f[i][0] = term == 0 ? -w[i] * vb[0] : 0.0;
        f[i][1] = term == 0 ? -w[i] * vb[1] : 0.0;
        f[i][2] = term == 1 ? w[i] * vb[2] : term == 2 ? -e2 : 0.0;
        for (a = 0; a < 3; a++) col[a] += f[i][a];
        col[3] += CORR_HUBS[i * 3 + 1] * f[i][2] - CORR_HUBS[i * 3 + 2] * f[i][1];
        col[4] += CORR_HUBS[i * 3 + 2] * f[i][0] - CORR_HUBS[i * 3 + 0] * f[i][2];
        col[5] += CORR_HUBS[i * 3 + 0] * f[i][1] - CORR_HUBS[i * 3 + 1] * f[i][0];
      }
    }
    for (i = 0; i < 3; i++) {
      h[i][t] = (R[i][0] * col[0] + R[i][1] * col[1] + R[i][2] * col[2]) / Y_STD[i];
      h[3 + i][t] = (R[i][0] * col[3] + R[i][1] * col[4] + R[i][2] * col[5]) / Y_STD[3 + i];
    }
  }
}
#endif

#if N_DELTA
/* delta_j's kernel row k[m_j] at xn, in loops over the points that vectorise (the points over
 * the lengthscales, input by input; exp without a call: as the global mean's); returns its
 * mean k . w */
HOT FUSED static double delta_row(int j, const double xn[D_IN], double *k) {
  const int n = DELTA_N[j];
  const double *Z = DELTA_ZL_T + DELTA_PT_OFF[j] * D_IN, *ls = DELTA_LS + j * D_IN;
  const double *w = DELTA_W + DELTA_PT_OFF[j];
  double s = 0.0;
  int p, i;
  for (p = 0; p < n; p++) k[p] = 0.0;
  for (i = 0; i < D_IN; i++) {
    const double *col = Z + (long)i * n, xl = xn[i] / ls[i];
    for (p = 0; p < n; p++) { double t = xl - col[p]; k[p] += t * t; }
  }
  for (p = 0; p < n; p++) k[p] = DELTA_SIGMA[j] * vexp(-0.5 * k[p]);
  for (p = 0; p < n; p++) s += k[p] * w[p];
  return s;
}
#endif

#if HAS_VAR && N_DELTA
/* |T k|^2 of a packed lower triangle T (row i: its i + 1 first entries), a dot product per
 * row. With GCC or clang its partial sums are vectors (four of 32 bytes: AVX2 in the cloned
 * version, and 64 bytes in a version for CPUs with AVX-512, picked at run time, as the
 * prior's variance); -DGPG_NO_VECTOR or another compiler: the scalar loop. A float T is
 * widened to double as it is loaded. */
#if (defined(__clang__) || (defined(__GNUC__) && __GNUC__ >= 9)) && !defined(GPG_NO_VECTOR)
#if TREAL_IS_DOUBLE
#define TLOAD(V, T_, P) memcpy(&(V), (P), sizeof(V))
#else
#define TLOAD(V, T_, P) \
  do { T_##_t t_; memcpy(&t_, (P), sizeof t_); (V) = __builtin_convertvector(t_, T_); } while (0)
#endif
#define TRI_SQ(NAME, T_, W)                                                                  \
  static double NAME(const treal *T, const double *k, int m) {                               \
    double q = 0.0, a;                                                                       \
    int i, c, j;                                                                             \
    for (i = 0; i < m; i++) {                                                                \
      T_ s0 = {0}, s1 = {0}, s2 = {0}, s3 = {0}, x, y;                                       \
      int n = i + 1;                                                                         \
      for (c = 0; c + 4 * (W) <= n; c += 4 * (W)) {                                          \
        TLOAD(x, T_, T + c); memcpy(&y, k + c, sizeof y); s0 += x * y;                       \
        TLOAD(x, T_, T + c + (W)); memcpy(&y, k + c + (W), sizeof y); s1 += x * y;           \
        TLOAD(x, T_, T + c + 2 * (W)); memcpy(&y, k + c + 2 * (W), sizeof y); s2 += x * y;   \
        TLOAD(x, T_, T + c + 3 * (W)); memcpy(&y, k + c + 3 * (W), sizeof y); s3 += x * y;   \
      }                                                                                      \
      for (; c + (W) <= n; c += (W)) {                                                       \
        TLOAD(x, T_, T + c); memcpy(&y, k + c, sizeof y); s0 += x * y;                       \
      }                                                                                      \
      s0 += s1; s2 += s3; s0 += s2;                                                          \
      a = 0.0;                                                                               \
      for (j = 0; j < (W); j++) a += s0[j];                                                  \
      for (; c < n; c++) a += (double)T[c] * k[c];                                           \
      T += n;                                                                                \
      q += a * a;                                                                            \
    }                                                                                        \
    return q;                                                                                \
  }
typedef double corr_v32 __attribute__((vector_size(32)));
typedef treal corr_v32_t __attribute__((vector_size(4 * sizeof(treal))));
HOT TRI_SQ(tri_sq_any, corr_v32, 4)
#if defined(GPG_CLONES) && !defined(GPG_NO_AVX512)
#pragma GCC push_options
#pragma GCC target("arch=x86-64-v4")
typedef double corr_v64 __attribute__((vector_size(64)));
typedef treal corr_v64_t __attribute__((vector_size(8 * sizeof(treal))));
TRI_SQ(tri_sq64, corr_v64, 8)
#pragma GCC pop_options
#else
#define tri_sq64 tri_sq_any
#endif
static double tri_sq(const treal *T, const double *k, int m) {
  return HAS_AVX512() ? tri_sq64(T, k, m) : tri_sq_any(T, k, m);
}
#else
static double tri_sq(const treal *T, const double *k, int m) {
  double q = 0.0, a;
  int i, c;
  for (i = 0; i < m; i++) {
    a = 0.0;
    for (c = 0; c <= i; c++) a += (double)T[c] * k[c];
    T += i + 1;
    q += a * a;
  }
  return q;
}
#endif
#endif

static void corrected(const double x[D_IN], const double xn[D_IN], double yn[N_OUT],
                      double latent, double *pv, double *dl) {
  double prior[N_OUT], ms[6] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0}, h[6][N_TERMS > 0 ? N_TERMS : 1];
#if N_DELTA
  double k[DELTA_MAX];
#endif
  int j, t;
  for (j = 0; j < N_OUT; j++) { prior[j] = yn[j]; yn[j] = CORR_SCALE[j] * prior[j]; }
#if HAS_KAPPA
  simple_columns(x, ms);
  for (j = 0; j < 6; j++) yn[j] += CORR_KAPPA[j] * ms[j];
#endif
#if N_TERMS
  physical_columns(x, h);
  for (j = 0; j < 6; j++)
    for (t = 0; t < N_TERMS; t++) yn[j] += CORR_BETA[j * N_TERMS + t] * h[j][t];
#endif
  if (pv)
    for (j = 0; j < N_OUT; j++)
      pv[j] = (latent > 0.0 ? latent : 0.0) * OUTPUT_SCALE[j] * CORR_SCALE[j] * CORR_SCALE[j];
#if N_DELTA
  for (j = 0; j < 6; j++) {
    yn[j] += delta_row(j, xn, k);
#if HAS_VAR
    if (pv) {
      double v = DELTA_SIGMA[j] - tri_sq(DELTA_TRI + DELTA_TRI_OFF[j], k, DELTA_N[j]);
      pv[j] += DELTA_OS[j] * ((v > 0.0 ? v : 0.0) + DELTA_NU[j]);
      if (dl) dl[j] = DELTA_OS[j] * (v > 0.0 ? v : 0.0); /* in a tracked model's band */
#if N_INTEGRATED
      {
        double hb[N_INTEGRATED], r[N_INTEGRATED], u;
        const double *G = CORR_G + DELTA_PT_OFF[j] * N_INTEGRATED;
        const double *C = CORR_C + j * N_INTEGRATED * N_INTEGRATED;
        int a = 0, p, q;
        if (CORR_WITH_PRIOR) hb[a++] = prior[j];
        if (CORR_WITH_SIMPLE) hb[a++] = ms[j];
        for (t = 0; t < N_TERMS; t++) hb[a++] = h[j][t];
        for (q = 0; q < N_INTEGRATED; q++) r[q] = hb[q];
        for (p = 0; p < DELTA_N[j]; p++) /* G row by row: contiguous, each r[q] in p's order */
          for (q = 0; q < N_INTEGRATED; q++) r[q] -= G[p * N_INTEGRATED + q] * k[p];
        for (q = 0; q < N_INTEGRATED; q++) {
          u = 0.0;
          for (p = 0; p < N_INTEGRATED; p++) u += C[p * N_INTEGRATED + q] * r[p];
          pv[j] += u * u;
        }
      }
#endif
    }
#endif
  }
#endif
  (void)ms; (void)h; (void)t; (void)latent; (void)dl;
}
