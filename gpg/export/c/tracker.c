
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

/* the members' mixture of h^T w per load output, and its variance h^T S h with the members'
 * spread, clipped at 0 (Tracker.mean_var) */
static void tracker_mix(const ONLINE_T *st, const double h[6][TRACK_P], double mix[6],
                        double var[6]) {
  double w[TRACK_K], m, v, sh, mean, second;
  int j, k, p, q;
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
    mix[j] = mean;
    v = second - mean * mean;
    var[j] = v > 0.0 ? v : 0.0;
  }
}

/* yn[j] += the members' mixture of h^T w; pv (when not null) gets the loads' band in place of
 * the offline one: the mixture's h^T S h with the members' spread, plus v_j, the labels'
 * offset's variance and delta_j's latent variance dl[j] (as Corrected's predictive_variance
 * with a tracker) */
static void tracker_eta(const ONLINE_T *st, const double x[D_IN], const double prior[N_OUT],
                        double yn[N_OUT], double *pv, const double dl[6]) {
  double h[6][TRACK_P], mix[6], var[6];
  int j;
  track_columns(x, prior, h);
  tracker_mix(st, h, mix, var);
  for (j = 0; j < 6; j++) {
    yn[j] += mix[j];
    if (pv) pv[j] = var[j] + (TRACK_NOISE[j] + TRACK_OFFSET[j]) + dl[j];
  }
}

/* relaxed to time t (never backwards): each member's OU step, a = exp(-dt/tau) for the basis's
 * columns and exp(-dt/tau_b,k) for the bias (and the wind state's, exp(-dt/tau_g)) */
HOT static void tracker_relax(ONLINE_T *st, double t) {
  double dt = t - st->t, a[TRACK_P], ab;
  int j, k, p, q;
  if (dt < 0.0) dt = 0.0;
  ab = exp(-dt / TRACK_TAU);
  for (p = 0; p < TRACK_P - 1; p++) a[p] = ab;
  for (k = 0; k < TRACK_K; k++) {
    a[TRACK_P - 1] = exp(-dt / TRACK_BIAS_TAU[k]);
    for (j = 0; j < 6; j++) {
      const double *S = TRACK_STAT + (long)j * TRACK_P * TRACK_P;
      for (p = 0; p < TRACK_P; p++) {
        real *row = st->cov[k][j][p];
        st->mean[k][j][p] = (real)(a[p] * (double)st->mean[k][j][p]);
        for (q = 0; q < TRACK_P; q++)
          row[q] = (real)(a[p] * a[q] * ((double)row[q] - S[p * TRACK_P + q]) + S[p * TRACK_P + q]);
      }
    }
  }
#if TRACK_WIND
  {
    double ag = exp(-dt / WIND_TAU), s2;
    for (p = 0; p < 3; p++) {
      st->wind_mean[p] = ag * st->wind_mean[p];
      for (q = 0; q < 3; q++) {
        s2 = p == q ? WIND_SD[p] * WIND_SD[p] : 0.0;
        st->wind_cov[p][q] = ag * ag * (st->wind_cov[p][q] - s2) + s2;
      }
    }
  }
#endif
  st->t += dt;
}

/* one rank-one Kalman step per member and output with the residual y (normalised, GP frame) of
 * noise variance r + v, and the members reweighed by their densities of the label, with the
 * fixed share (not relaxed first: tracker_relax). S stays exactly symmetric: the step
 * subtracts (sp_p sp_q) / s, the same number on both sides (the library symmetrises after it:
 * the two agree to rounding). */
HOT static void tracker_measure(ONLINE_T *st, const double h[6][TRACK_P], const double y[6],
                                const double r[6]) {
  double sp[TRACK_P], joint[TRACK_K], s, e, inv, top, total;
  int j, k, p, q;
  for (k = 0; k < TRACK_K; k++) {
    joint[k] = st->log_weight[k];
    for (j = 0; j < 6; j++) {
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
}

#if TRACK_WIND
/* The wind state's Kalman step linearised at its mean (Tracker.wind_measured): e the label's
 * residual there, J its derivative in the wind (6 x 3), n the innovation's own variance (the
 * label's noise, delta's latent variance, v and the coefficients' band h^T S h) and m the
 * coefficients' mixture (not yet told the label). H = -J; the gain P H^T S^-1 by a Cholesky
 * factor of the 6 x 6 S = H P H^T + diag(n); P - gain H P symmetrised, as the library. */
static void wind_kalman(ONLINE_T *st, const double e[6], const double J[6][3], const double n[6],
                        const double m[6]) {
  double PHt[3][6], S[6][6], L[6][6], X[6][3], cov[3][3], d;
  int i, j, a, b;
  for (a = 0; a < 3; a++)
    for (j = 0; j < 6; j++) {
      PHt[a][j] = 0.0;
      for (b = 0; b < 3; b++) PHt[a][j] -= st->wind_cov[a][b] * J[j][b];
    }
  for (i = 0; i < 6; i++)
    for (j = 0; j < 6; j++) {
      S[i][j] = i == j ? n[i] : 0.0;
      for (a = 0; a < 3; a++) S[i][j] -= J[i][a] * PHt[a][j];
    }
  for (i = 0; i < 6; i++) /* S = L L^T */
    for (j = 0; j <= i; j++) {
      d = 0.5 * (S[i][j] + S[j][i]);
      for (a = 0; a < j; a++) d -= L[i][a] * L[j][a];
      if (i == j) L[i][i] = sqrt(d > 0.0 ? d : 0.0);
      else L[i][j] = d / L[j][j];
    }
  for (a = 0; a < 3; a++) { /* X = S^-1 (P H^T)^T, column a */
    for (i = 0; i < 6; i++) {
      d = PHt[a][i];
      for (j = 0; j < i; j++) d -= L[i][j] * X[j][a];
      X[i][a] = d / L[i][i];
    }
    for (i = 5; i >= 0; i--) {
      d = X[i][a];
      for (j = i + 1; j < 6; j++) d -= L[j][i] * X[j][a];
      X[i][a] = d / L[i][i];
    }
  }
  for (a = 0; a < 3; a++) {
    d = 0.0;
    for (j = 0; j < 6; j++) d += X[j][a] * (e[j] - m[j]);
    st->wind_mean[a] += d;
    for (b = 0; b < 3; b++) {
      d = st->wind_cov[a][b];
      for (j = 0; j < 6; j++) d -= X[j][a] * PHt[b][j];
      cov[a][b] = d;
    }
  }
  for (a = 0; a < 3; a++)
    for (b = 0; b < 3; b++) st->wind_cov[a][b] = 0.5 * (cov[a][b] + cov[b][a]);
}
#endif
