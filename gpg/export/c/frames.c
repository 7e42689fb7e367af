
/* R = Rz(yaw) Ry(pitch) Rx(roll) */
static void rot_wb(double yaw, double pitch, double roll, double R[3][3]) {
  double cy = cos(yaw), sy = sin(yaw), cp = cos(pitch), sp = sin(pitch);
  double cr = cos(roll), sr = sin(roll);
  R[0][0] = cy * cp; R[0][1] = cy * sp * sr - sy * cr; R[0][2] = cy * sp * cr + sy * sr;
  R[1][0] = sy * cp; R[1][1] = sy * sp * sr + cy * cr; R[1][2] = sy * sp * cr - cy * sr;
  R[2][0] = -sp;     R[2][1] = cp * sr;                R[2][2] = cp * cr;
}

#if !BODY_FRAME
static double safe_atan2(double y, double x, double tiny) {
  if (fabs(x) <= tiny && fabs(y) <= tiny) return 0.0;
  return atan2(y, x);
}

static double norm3(const double v[3]) {
  double s = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
  return s <= 0.0 ? 0.0 : sqrt(s);
}

/* wind axes Rz(heading) Ry(climb) of the direction d */
static void wind_axes(const double d[3], double R[3][3]) {
  double dxy[3] = {d[0], d[1], 0.0};
  double heading = safe_atan2(d[1], d[0], TINY_SPEED);
  double climb = safe_atan2(-d[2], norm3(dxy), TINY_SPEED);
  rot_wb(heading, climb, 0.0, R);
}

/* R_WH of the airflow frame, blended toward the body heading (gpg.quadrotor.frames); cy, sy
 * the heading's cosine and sine */
static void airflow_frame(const double v[3], double cy, double sy, double R[3][3]) {
  double h = HOVER_SPEED, d[3], x[3], y[3], z[3], c, dxy2, n, yx;
  int i;
  if (h <= 0.0) { wind_axes(v, R); return; }
  c = 1.0 - (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) / (h * h);
  c = h * (c > 0.0 ? c * c : 0.0);
  d[0] = v[0] + c * cy; d[1] = v[1] + c * sy; d[2] = v[2];
  dxy2 = d[0] * d[0] + d[1] * d[1];
  if (dxy2 >= h * h) { wind_axes(d, R); return; }
  n = d[0] * d[0] + d[1] * d[1] + d[2] * d[2] > 0.0 ? norm3(d) : 1.0;
  for (i = 0; i < 3; i++) x[i] = d[i] / n;
  c = 1.0 - dxy2 / (h * h);
  c = h * (c > 0.0 ? c * c : 0.0);
  y[0] = -d[1] - c * sy; y[1] = d[0] + c * cy; y[2] = 0.0;
  yx = y[0] * x[0] + y[1] * x[1] + y[2] * x[2];
  for (i = 0; i < 3; i++) y[i] -= yx * x[i];
  n = y[0] * y[0] + y[1] * y[1] + y[2] * y[2] > 0.0 ? norm3(y) : 1.0;
  for (i = 0; i < 3; i++) y[i] /= n;
  z[0] = x[1] * y[2] - x[2] * y[1];
  z[1] = x[2] * y[0] - x[0] * y[2];
  z[2] = x[0] * y[1] - x[1] * y[0];
  for (i = 0; i < 3; i++) { R[i][0] = x[i]; R[i][1] = y[i]; R[i][2] = z[i]; }
}

static void euler_from_r(double R[3][3], double e[3]) {
  double cp = hypot(R[0][0], R[1][0]);
  e[1] = safe_atan2(-R[2][0], cp, 0.0);
  if (cp < 1e-12) { e[0] = safe_atan2(-R[0][1], R[1][1], 0.0); e[2] = 0.0; }
  else { e[0] = safe_atan2(R[1][0], R[0][0], 0.0); e[2] = safe_atan2(R[2][1], R[2][2], 0.0); }
}

/* the attitude R_WB (its yaw's cosine cy and sine sy) in the airflow frame of v, and R_WH */
static void airflow_at(const double rwb[3][3], double cy, double sy, const double v[3],
                       double eh[3], double rwh[3][3]) {
  double rhb[3][3];
  int i, j, k;
  airflow_frame(v, cy, sy, rwh);
  for (i = 0; i < 3; i++)
    for (j = 0; j < 3; j++) {
      rhb[i][j] = 0.0;
      for (k = 0; k < 3; k++) rhb[i][j] += rwh[k][i] * rwb[k][j];
    }
  euler_from_r(rhb, eh);
}

/* the attitude in the airflow frame, and R_WH */
static void to_airflow(const double euler[3], const double v[3], double eh[3], double rwh[3][3]) {
  double rwb[3][3];
  rot_wb(euler[0], euler[1], euler[2], rwb);
  airflow_at(rwb, cos(euler[0]), sin(euler[0]), v, eh, rwh);
}

/* frames.airflow_frame_rate by central differences (rad per m/s); the attitude's rotation and
 * its yaw's cosine and sine once, not at each of the six air velocities */
static double frame_rate(const double euler[3], const double v[3]) {
  double se = 0.0, sr = 0.0, step = 1e-6, vp[3], vm[3], ep[3], em[3], rp[3][3], rm[3][3], t;
  double rwb[3][3], cy, sy;
  int j, a, b;
  if (HOVER_SPEED <= 0.0 && v[0] * v[0] + v[1] * v[1] <= TINY_SPEED * TINY_SPEED) return INFINITY;
  rot_wb(euler[0], euler[1], euler[2], rwb);
  cy = cos(euler[0]);
  sy = sin(euler[0]);
  for (j = 0; j < 3; j++) {
    for (a = 0; a < 3; a++) { vp[a] = v[a]; vm[a] = v[a]; }
    vp[j] += step; vm[j] -= step;
    airflow_at(rwb, cy, sy, vp, ep, rp);
    airflow_at(rwb, cy, sy, vm, em, rm);
    for (a = 0; a < 3; a++) {
      t = ep[a] - em[a];
      t -= 6.283185307179586 * floor((t + 3.141592653589793) / 6.283185307179586);
      se += t * t;
      for (b = 0; b < 3; b++) { t = rp[a][b] - rm[a][b]; sr += t * t; }
    }
  }
  se = sqrt(se) / (2.0 * step);
  sr = sqrt(sr / 2.0) / (2.0 * step);
  return se > sr ? se : sr;
}
#endif
