
/* The online term eta of an adapted model (gpg.flight.correction.Online,
 * gpg.export.layout.OnlineTerm): per load output j, psi_j = W_j k_j(xn, Z), mean psi_j . mu_j,
 * variance psi_j^T S_j psi_j. Its state (ONLINE_T: mu, S in `real`, the time in double) is
 * the caller's; nothing is allocated. The sums run in double whatever `real` is. */

/* psi[6][N_IND] at xn */
static void online_features(const double xn[D_IN], double psi[6][N_IND]) {
  double k[N_IND], r2, t;
  int j, p, i, c;
  for (j = 0; j < 6; j++) {
    const double *ls = ONLINE_LS + j * D_IN;
    const double *W = ONLINE_WHITEN + (long)j * N_IND * N_IND;
    for (p = 0; p < N_IND; p++) {
      r2 = 0.0;
      for (i = 0; i < D_IN; i++) { t = (xn[i] - ONLINE_Z[p * D_IN + i]) / ls[i]; r2 += t * t; }
      k[p] = ONLINE_VAR[j] * exp(-0.5 * r2);
    }
    for (p = 0; p < N_IND; p++) {
      t = 0.0;
      for (c = 0; c < N_IND; c++) t += W[p * N_IND + c] * k[c];
      psi[j][p] = t;
    }
  }
}

/* yn += eta's mean; pv (when not null) += max(eta's variance, 0), normalised */
static void online_eta(const ONLINE_T *st, const double xn[D_IN], double yn[N_OUT], double *pv) {
  double psi[6][N_IND], m, v, sp;
  int j, p, q;
  online_features(xn, psi);
  for (j = 0; j < 6; j++) {
    m = 0.0;
    for (p = 0; p < N_IND; p++) m += psi[j][p] * (double)st->mean[j][p];
    yn[j] += m;
    if (!pv) continue;
    v = 0.0;
    for (p = 0; p < N_IND; p++) {
      sp = 0.0;
      for (q = 0; q < N_IND; q++) sp += (double)st->cov[j][p][q] * psi[j][q];
      v += psi[j][p] * sp;
    }
    pv[j] += v > 0.0 ? v : 0.0;
  }
}

/* relaxed to time t (never backwards), then one rank-one Kalman step per output with the
 * residual y (normalised, GP frame) of noise variance r */
static void online_kalman(ONLINE_T *st, double t, const double xn[D_IN], const double y[6],
                          const double r[6]) {
  double psi[6][N_IND], sp[N_IND], dt = t - st->t, a, a2, s, e, gain;
  int j, p, q;
  if (dt < 0.0) dt = 0.0;
  a = exp(-dt / ONLINE_TAU);
  a2 = a * a;
  online_features(xn, psi);
  for (j = 0; j < 6; j++) {
    for (p = 0; p < N_IND; p++) {
      st->mean[j][p] = (real)(a * (double)st->mean[j][p]);
      for (q = 0; q < N_IND; q++)
        st->cov[j][p][q] = (real)(a2 * (double)st->cov[j][p][q] + (p == q ? 1.0 - a2 : 0.0));
    }
    s = r[j] + ONLINE_NU[j];
    e = y[j];
    for (p = 0; p < N_IND; p++) {
      sp[p] = 0.0;
      for (q = 0; q < N_IND; q++) sp[p] += (double)st->cov[j][p][q] * psi[j][q];
      s += psi[j][p] * sp[p];
      e -= psi[j][p] * (double)st->mean[j][p];
    }
    for (p = 0; p < N_IND; p++) {
      gain = sp[p] / s;
      st->mean[j][p] = (real)((double)st->mean[j][p] + gain * e);
      for (q = 0; q < N_IND; q++) st->cov[j][p][q] = (real)((double)st->cov[j][p][q] - gain * sp[q]);
    }
    /* symmetric under rounding, as the library keeps it */
    for (p = 0; p < N_IND; p++)
      for (q = 0; q < p; q++) {
        double m = 0.5 * ((double)st->cov[j][p][q] + (double)st->cov[j][q][p]);
        st->cov[j][p][q] = (real)m;
        st->cov[j][q][p] = (real)m;
      }
  }
  st->t += dt;
}
