
/* The online term eta of an adapted model (gpg.flight.correction.Online,
 * gpg.export.layout.OnlineTerm): per load output j, psi_j = W_j k_j(xn, Z), mean psi_j . mu_j,
 * variance psi_j^T S_j psi_j. Its state (ONLINE_T: mu, S in `real`, the time in double) is
 * the caller's; nothing is allocated. The sums run in double whatever `real` is. A bank
 * (bank.c) has ONLINE_K such terms, member k's constants at offset k in each array. */

/* psi[6][N_IND] of member k at xn: column by column of W_j (ONLINE_WHITEN_T holds W_j^T, its
 * columns contiguous), so that the inner loop is an axpy the compiler vectorises; each psi_p
 * sums in the row's own order */
HOT static void online_features(int m, const double xn[D_IN], double psi[6][N_IND]) {
  double k[N_IND], r2, t;
  const double *Z = ONLINE_Z + (long)m * N_IND * D_IN;
  int j, p, i, c;
  for (j = 0; j < 6; j++) {
    const double *ls = ONLINE_LS + ((long)m * 6 + j) * D_IN;
    const double *WT = ONLINE_WHITEN_T + ((long)m * 6 + j) * N_IND * N_IND;
    for (p = 0; p < N_IND; p++) {
      r2 = 0.0;
      for (i = 0; i < D_IN; i++) { t = (xn[i] - Z[p * D_IN + i]) / ls[i]; r2 += t * t; }
      k[p] = ONLINE_VAR[m * 6 + j] * exp(-0.5 * r2);
      psi[j][p] = 0.0;
    }
    for (c = 0; c < N_IND; c++) {
      const double *col = WT + (long)c * N_IND, kc = k[c];
      for (p = c; p < N_IND; p++) psi[j][p] += kc * col[p];
    }
  }
}

/* a term's moments at its features psi, per load output: mean psi . mu, variance
 * psi^T S psi, and psi^T psi (the share of the offline band its prior takes); with a (not
 * null) the state relaxed by the factors a first (mu <- a mu, S <- a S a + I - a^2), not
 * stored */
static void online_moments(const real mean[6][N_IND], const real cov[6][N_IND][N_IND],
                           const double psi[6][N_IND], const double (*a)[N_IND], double m[6],
                           double v[6], double q[6]) {
  double phi[N_IND], sp[N_IND];
  int j, p, r;
  for (j = 0; j < 6; j++) {
    m[j] = 0.0;
    v[j] = 0.0;
    q[j] = 0.0;
    for (p = 0; p < N_IND; p++) {
      phi[p] = a ? a[j][p] * psi[j][p] : psi[j][p];
      m[j] += phi[p] * (double)mean[j][p];
      q[j] += psi[j][p] * psi[j][p];
      if (a) v[j] += (1.0 - a[j][p] * a[j][p]) * psi[j][p] * psi[j][p];
      sp[p] = 0.0;
    }
    for (r = 0; r < N_IND; r++) /* S phi by rows of the symmetric S */
      for (p = 0; p < N_IND; p++) sp[p] += (double)cov[j][r][p] * phi[r];
    for (p = 0; p < N_IND; p++) v[j] += phi[p] * sp[p];
  }
}

/* a term's band from the offline one b (normalised): with ONLINE_SHARED, eta's prior is a
 * share of it (gpg.flight.adapt's band="shared"): max(b - psi^T psi, 0) + psi^T S psi */
static double online_band(double b, double v, double q) {
  if (ONLINE_SHARED) b = b > q ? b - q : 0.0;
  return b + (v > 0.0 ? v : 0.0);
}

#if !IS_BANK
/* yn += eta's mean; pv (when not null; the offline band, complete here) becomes eta's band */
static void online_eta(const ONLINE_T *st, const double xn[D_IN], double yn[N_OUT], double *pv) {
  double psi[6][N_IND], m[6], v[6], q[6];
  int j;
  online_features(0, xn, psi);
  online_moments((const real(*)[N_IND])st->mean, (const real(*)[N_IND][N_IND])st->cov, psi, 0,
                 m, v, q);
  for (j = 0; j < 6; j++) {
    yn[j] += m[j];
    if (pv) pv[j] = online_band(pv[j], v[j], q[j]);
  }
}
#endif

/* member k's state (mean, cov, its time *tp) relaxed to time t (never backwards), then one
 * rank-one Kalman step per output with the residual y (normalised, GP frame) of noise
 * variance r. S stays exactly symmetric: the step subtracts (sp_p sp_q) / s, the same number
 * on both sides (the library symmetrises after the step instead: the two agree to
 * rounding). */
HOT static void online_kalman(int k, real mean[6][N_IND], real cov[6][N_IND][N_IND],
                              double *tp, double t, const double xn[D_IN], const double y[6],
                              const double r[6]) {
  double psi[6][N_IND], sp[N_IND], a[N_IND], dt = t - *tp, s, e, inv;
  int j, p, q;
  if (dt < 0.0) dt = 0.0;
  online_features(k, xn, psi);
  for (j = 0; j < 6; j++) {
    /* each weight's own OU factor (one time constant per output, or per weight) */
    for (p = 0; p < N_IND; p++) a[p] = exp(-dt / ONLINE_TAU[((long)k * 6 + j) * N_IND + p]);
    for (p = 0; p < N_IND; p++) {
      real *row = cov[j][p];
      mean[j][p] = (real)(a[p] * (double)mean[j][p]);
      for (q = 0; q < N_IND; q++) row[q] = (real)((a[p] * a[q]) * (double)row[q]);
      row[p] = (real)((double)row[p] + (1.0 - a[p] * a[p]));
    }
    for (p = 0; p < N_IND; p++) sp[p] = 0.0;
    for (q = 0; q < N_IND; q++) {
      const real *row = cov[j][q];
      const double w = psi[j][q];
      for (p = 0; p < N_IND; p++) sp[p] += (double)row[p] * w;
    }
    s = r[j] + ONLINE_NU[k * 6 + j];
    e = y[j];
    for (p = 0; p < N_IND; p++) {
      s += psi[j][p] * sp[p];
      e -= psi[j][p] * (double)mean[j][p];
    }
    inv = 1.0 / s;
    for (p = 0; p < N_IND; p++) {
      real *row = cov[j][p];
      const double g = sp[p] * inv;
      mean[j][p] = (real)((double)mean[j][p] + g * e);
      for (q = 0; q < N_IND; q++) row[q] = (real)((double)row[q] - (sp[p] * sp[q]) * inv);
    }
  }
  *tp += dt;
}
