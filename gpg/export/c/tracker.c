
/* The tracked coefficients of a model prepared by gpg.flight.track (gpg.flight.tracking.Tracker,
 * gpg.export.layout.TrackedTerm): a bank of TRACK_K Kalman filters on the drift w of the
 * columns h = (the prior's mean, M's loads where tracked, the physical terms, a bias) per load
 * output. Its state (ONLINE_T: the members' means and covariances in `real`, their log weights
 * and the time in double) is the caller's; nothing is allocated. The sums run in double. */

/* the columns h[6][TRACK_P] at x, from the prior's normalised mean (Corrected.tracker_columns) */
static void track_columns(const double x[D_IN], const double prior[N_OUT], double h[6][TRACK_P]) {
  double ms[6] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0}, ph[6][N_TERMS];
  int j, t, a;
#if TRACK_SIMPLE
  simple_columns(x, ms);
#endif
  physical_columns(x, ph);
  for (j = 0; j < 6; j++) {
    a = 0;
    h[j][a++] = prior[j];
#if TRACK_SIMPLE
    h[j][a++] = ms[j];
#endif
    for (t = 0; t < N_TERMS; t++) h[j][a++] = ph[j][t];
    h[j][a] = TRACK_BIAS[j];
  }
}

/* yn[j] += the members' mixture of h^T w; pv (when not null) gets the loads' band in place of
 * the offline one: the mixture's h^T S h with the members' spread, plus v_j, the labels'
 * offset's variance and delta_j's latent variance dl[j] (as Corrected's predictive_variance
 * with a tracker) */
static void tracker_eta(const ONLINE_T *st, const double x[D_IN], const double prior[N_OUT],
                        double yn[N_OUT], double *pv, const double dl[6]) {
  double h[6][TRACK_P], w[TRACK_K], m, v, sh, mean, second;
  int j, k, p, q;
  track_columns(x, prior, h);
  for (k = 0; k < TRACK_K; k++) w[k] = exp(st->log_weight[k]);
  for (j = 0; j < 6; j++) {
    mean = 0.0;
    second = 0.0;
    for (k = 0; k < TRACK_K; k++) {
      m = 0.0;
      v = 0.0;
      for (p = 0; p < TRACK_P; p++) {
        m += h[j][p] * (double)st->mean[k][j][p];
        sh = 0.0;
        for (q = 0; q < TRACK_P; q++) sh += (double)st->cov[k][j][p][q] * h[j][q];
        v += h[j][p] * sh;
      }
      mean += w[k] * m;
      second += w[k] * (v + m * m);
    }
    yn[j] += mean;
    if (pv) {
      v = second - mean * mean;
      pv[j] = (v > 0.0 ? v : 0.0) + (TRACK_NOISE[j] + TRACK_OFFSET[j]) + dl[j];
    }
  }
}

/* relaxed to time t (never backwards): each member's OU step, a = exp(-dt/tau) for the basis's
 * columns and exp(-dt/tau_b,k) for the bias; then one rank-one Kalman step per member and output
 * with the residual y (normalised, GP frame) of noise variance r + v, and the members reweighed
 * by their densities of the label, with the fixed share. S stays exactly symmetric: the step
 * subtracts (sp_p sp_q) / s, the same number on both sides (the library symmetrises after it:
 * the two agree to rounding). */
HOT static void tracker_kalman(ONLINE_T *st, double t, const double h[6][TRACK_P],
                               const double y[6], const double r[6]) {
  double dt = t - st->t, a[TRACK_P], sp[TRACK_P], joint[TRACK_K], s, e, inv, top, total, ab;
  int j, k, p, q;
  if (dt < 0.0) dt = 0.0;
  ab = exp(-dt / TRACK_TAU);
  for (p = 0; p < TRACK_P - 1; p++) a[p] = ab;
  for (k = 0; k < TRACK_K; k++) {
    a[TRACK_P - 1] = exp(-dt / TRACK_BIAS_TAU[k]);
    joint[k] = st->log_weight[k];
    for (j = 0; j < 6; j++) {
      const double *S = TRACK_STAT + (long)j * TRACK_P * TRACK_P;
      for (p = 0; p < TRACK_P; p++) {
        real *row = st->cov[k][j][p];
        st->mean[k][j][p] = (real)(a[p] * (double)st->mean[k][j][p]);
        for (q = 0; q < TRACK_P; q++)
          row[q] = (real)(a[p] * a[q] * ((double)row[q] - S[p * TRACK_P + q]) + S[p * TRACK_P + q]);
      }
      for (p = 0; p < TRACK_P; p++) {
        sp[p] = 0.0;
        for (q = 0; q < TRACK_P; q++) sp[p] += (double)st->cov[k][j][p][q] * h[j][q];
      }
      s = r[j] + TRACK_NOISE[j];
      e = y[j];
      for (p = 0; p < TRACK_P; p++) {
        s += h[j][p] * sp[p];
        e -= h[j][p] * (double)st->mean[k][j][p];
      }
      inv = 1.0 / s;
      for (p = 0; p < TRACK_P; p++) {
        real *row = st->cov[k][j][p];
        st->mean[k][j][p] = (real)((double)st->mean[k][j][p] + sp[p] * inv * e);
        for (q = 0; q < TRACK_P; q++) row[q] = (real)((double)row[q] - (sp[p] * sp[q]) * inv);
      }
      joint[k] += -0.5 * (log(2.0 * 3.14159265358979323846 * s) + e * e * inv);
    }
  }
  top = joint[0];
  for (k = 1; k < TRACK_K; k++) if (joint[k] > top) top = joint[k];
  total = 0.0;
  for (k = 0; k < TRACK_K; k++) total += exp(joint[k] - top);
  total = top + log(total);
  for (k = 0; k < TRACK_K; k++)
    st->log_weight[k] =
        log((1.0 - TRACK_SHARE) * exp(joint[k] - total) + TRACK_SHARE / TRACK_K);
  st->t += dt;
}
