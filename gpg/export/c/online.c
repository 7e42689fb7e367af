
/* The online term eta of an adapted model (gpg.flight.correction.Online,
 * gpg.export.layout.OnlineTerm): per load output j, psi_j = W_j k_j(xn, Z), mean psi_j . mu_j,
 * variance psi_j^T S_j psi_j. Its state (ONLINE_T: mu, S in `real`, the time in double) is
 * the caller's; nothing is allocated. The sums run in double whatever `real` is. */

/* psi[6][N_IND] at xn: column by column of W_j (ONLINE_WHITEN_T holds W_j^T, its columns
 * contiguous), so that the inner loop is an axpy the compiler vectorises; each psi_p sums in
 * the row's own order */
HOT static void online_features(const double xn[D_IN], double psi[6][N_IND]) {
  double k[N_IND], r2, t;
  int j, p, i, c;
  for (j = 0; j < 6; j++) {
    const double *ls = ONLINE_LS + j * D_IN;
    const double *WT = ONLINE_WHITEN_T + (long)j * N_IND * N_IND;
    for (p = 0; p < N_IND; p++) {
      r2 = 0.0;
      for (i = 0; i < D_IN; i++) { t = (xn[i] - ONLINE_Z[p * D_IN + i]) / ls[i]; r2 += t * t; }
      k[p] = ONLINE_VAR[j] * exp(-0.5 * r2);
      psi[j][p] = 0.0;
    }
    for (c = 0; c < N_IND; c++) {
      const double *col = WT + (long)c * N_IND, kc = k[c];
      for (p = c; p < N_IND; p++) psi[j][p] += kc * col[p];
    }
  }
}

/* yn += eta's mean; pv (when not null) += max(eta's variance, 0), normalised; with
 * ONLINE_SHARED, pv (the offline band, complete here) = max(pv - psi^T psi, 0) + that variance:
 * eta's prior is a share of the offline band (gpg.flight.adapt's band="shared") */
static void online_eta(const ONLINE_T *st, const double xn[D_IN], double yn[N_OUT], double *pv) {
  double psi[6][N_IND], sp[N_IND], m, v, q0;
  int j, p, q;
  online_features(xn, psi);
  for (j = 0; j < 6; j++) {
    m = 0.0;
    for (p = 0; p < N_IND; p++) m += psi[j][p] * (double)st->mean[j][p];
    yn[j] += m;
    if (!pv) continue;
    for (p = 0; p < N_IND; p++) sp[p] = 0.0;
    for (q = 0; q < N_IND; q++) /* S psi by rows of the symmetric S */
      for (p = 0; p < N_IND; p++) sp[p] += (double)st->cov[j][q][p] * psi[j][q];
    v = 0.0;
    q0 = 0.0;
    for (p = 0; p < N_IND; p++) { v += psi[j][p] * sp[p]; q0 += psi[j][p] * psi[j][p]; }
    if (ONLINE_SHARED) pv[j] = pv[j] > q0 ? pv[j] - q0 : 0.0;
    pv[j] += v > 0.0 ? v : 0.0;
  }
}

/* relaxed to time t (never backwards), then one rank-one Kalman step per output with the
 * residual y (normalised, GP frame) of noise variance r. S stays exactly symmetric: the step
 * subtracts (sp_p sp_q) / s, the same number on both sides (the library symmetrises after
 * the step instead: the two agree to rounding). */
HOT static void online_kalman(ONLINE_T *st, double t, const double xn[D_IN], const double y[6],
                              const double r[6]) {
  double psi[6][N_IND], sp[N_IND], a[N_IND], dt = t - st->t, s, e, inv;
  int j, p, q;
  if (dt < 0.0) dt = 0.0;
  online_features(xn, psi);
  for (j = 0; j < 6; j++) {
    /* each weight's own OU factor (one time constant per output, or per weight) */
    for (p = 0; p < N_IND; p++) a[p] = exp(-dt / ONLINE_TAU[j * N_IND + p]);
    for (p = 0; p < N_IND; p++) {
      real *row = st->cov[j][p];
      st->mean[j][p] = (real)(a[p] * (double)st->mean[j][p]);
      for (q = 0; q < N_IND; q++) row[q] = (real)((a[p] * a[q]) * (double)row[q]);
      row[p] = (real)((double)row[p] + (1.0 - a[p] * a[p]));
    }
    for (p = 0; p < N_IND; p++) sp[p] = 0.0;
    for (q = 0; q < N_IND; q++) {
      const real *row = st->cov[j][q];
      const double w = psi[j][q];
      for (p = 0; p < N_IND; p++) sp[p] += (double)row[p] * w;
    }
    s = r[j] + ONLINE_NU[j];
    e = y[j];
    for (p = 0; p < N_IND; p++) {
      s += psi[j][p] * sp[p];
      e -= psi[j][p] * (double)st->mean[j][p];
    }
    inv = 1.0 / s;
    for (p = 0; p < N_IND; p++) {
      real *row = st->cov[j][p];
      const double g = sp[p] * inv;
      st->mean[j][p] = (real)((double)st->mean[j][p] + g * e);
      for (q = 0; q < N_IND; q++) row[q] = (real)((double)row[q] - (sp[p] * sp[q]) * inv);
    }
  }
  st->t += dt;
}
