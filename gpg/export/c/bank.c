
/* A bank of ONLINE_K online terms mixed by their predictions BANK_L labels ahead
 * (gpg.flight.Bank, gpg.export.layout.BankTerm). Each member runs twice: as it is, for the
 * predictions, and BANK_L labels late (lag_*), its updates waiting in a ring of the last
 * BANK_L labels, for the scores. Member k's log weight per load output adds the log density of
 * each label under its lagged copy's band (composed with the offline band at the label, as the
 * member's own) and decays by exp(-dt / BANK_WTAU) between labels. */

#define BANK_TWO_PI 6.283185307179586

/* yn += the mixture's mean sum_k w_k eta_k; pv (when not null; the offline band, complete
 * here) becomes sum_k w_k band_k plus the spread of the members' means */
static void online_eta(const ONLINE_T *st, const double xn[D_IN], double yn[N_OUT], double *pv) {
  double psi[6][N_IND], m[ONLINE_K][6], v[ONLINE_K][6], q[ONLINE_K][6], w[ONLINE_K], top, sum;
  double mix, second, band;
  int k, j;
  for (k = 0; k < ONLINE_K; k++) {
    online_features(k, xn, psi);
    online_moments((const real(*)[N_IND])st->mean[k], (const real(*)[N_IND][N_IND])st->cov[k],
                   psi, 0, m[k], v[k], q[k]);
  }
  for (j = 0; j < 6; j++) {
    top = st->log_weight[0][j];
    for (k = 1; k < ONLINE_K; k++) if (st->log_weight[k][j] > top) top = st->log_weight[k][j];
    sum = 0.0;
    for (k = 0; k < ONLINE_K; k++) { w[k] = exp(st->log_weight[k][j] - top); sum += w[k]; }
    mix = 0.0;
    second = 0.0;
    band = 0.0;
    for (k = 0; k < ONLINE_K; k++) {
      w[k] /= sum;
      mix += w[k] * m[k][j];
      second += w[k] * m[k][j] * m[k][j];
      if (pv) band += w[k] * online_band(pv[j], v[k][j], q[k][j]);
    }
    yn[j] += mix;
    if (pv) pv[j] = band + (second > mix * mix ? second - mix * mix : 0.0);
  }
}

/* one label at time t: its normalised input xn, residual y against the offline mean, noise
 * variance r and the offline band b there (normalised, GP frame), as gpg.flight.Bank's
 * relaxed and measured */
static void bank_update(ONLINE_T *st, double t, const double xn[D_IN], const double y[6],
                        const double r[6], const double b[6]) {
  double psi[6][N_IND], a[6][N_IND], m[6], v[6], q[6], dt = t - st->t, lag, s, top, tk;
  int k, j, p, slot = (int)(st->count % BANK_L);
  if (dt < 0.0) dt = 0.0;
  t = st->t + dt;
  for (k = 0; k < ONLINE_K; k++)
    for (j = 0; j < 6; j++) st->log_weight[k][j] *= exp(-dt / BANK_WTAU);
  for (k = 0; k < ONLINE_K; k++) {
    if (st->ring_live[slot]) /* the label BANK_L before, to the lagged copies */
      online_kalman(k, st->lag_mean[k], st->lag_cov[k], &st->lag_t[k], st->ring_t[slot],
                    st->ring_x[slot], st->ring_y[slot], st->ring_r[slot]);
    /* the lagged copy's prediction of this label, relaxed to t (not stored) */
    lag = t - st->lag_t[k];
    if (lag < 0.0) lag = 0.0;
    for (j = 0; j < 6; j++)
      for (p = 0; p < N_IND; p++)
        a[j][p] = exp(-lag / ONLINE_TAU[((long)k * 6 + j) * N_IND + p]);
    online_features(k, xn, psi);
    online_moments((const real(*)[N_IND])st->lag_mean[k],
                   (const real(*)[N_IND][N_IND])st->lag_cov[k], psi, (const double(*)[N_IND])a,
                   m, v, q);
    for (j = 0; j < 6; j++) {
      s = online_band(b[j], v[j], q[j]) + r[j];
      st->log_weight[k][j] += -0.5 * (log(BANK_TWO_PI * s) + (y[j] - m[j]) * (y[j] - m[j]) / s);
    }
  }
  for (j = 0; j < 6; j++) { /* a constant per output: kept small */
    top = st->log_weight[0][j];
    for (k = 1; k < ONLINE_K; k++) if (st->log_weight[k][j] > top) top = st->log_weight[k][j];
    for (k = 0; k < ONLINE_K; k++) st->log_weight[k][j] -= top;
  }
  for (k = 0; k < ONLINE_K; k++) { /* every member, relaxed to t, takes the label */
    tk = st->t;
    online_kalman(k, st->mean[k], st->cov[k], &tk, t, xn, y, r);
  }
  for (p = 0; p < D_IN; p++) st->ring_x[slot][p] = xn[p];
  for (j = 0; j < 6; j++) { st->ring_y[slot][j] = y[j]; st->ring_r[slot][j] = r[j]; }
  st->ring_t[slot] = t;
  st->ring_live[slot] = 1;
  st->count += 1;
  st->t = t;
}
