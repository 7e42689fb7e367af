/* A closed-loop flight in C with a gpg surrogate exported by gpg.export.to_c: the rigid body
 * and motors of gpg.quadrotor.dynamics (RK4, the aerodynamic wrench held over each step), the
 * geometric SE(3) controller and the minimum-jerk waypoint plan of gpg.quadrotor.control, in
 * a mean wind plus a sinusoidal gust: the flight of `python -m experiments.simulate`.
 *
 * Build (the parameters header from gpg.export.flight.write_params, which also names the
 * model's header and function):
 *   cc -O2 -std=c99 -I<dir of flight_params.h and the model> flight.c <model>.c -lm
 * Run: ./a.out > trace.csv  (one line a step: t, p[3], v[3], rpm[4], in_domain)
 */
#include <math.h>
#include <stdio.h>

#include "flight_params.h"

typedef struct { double p[3], v[3], q[4], w[3], rpm[4]; } State;

static void quat_to_R(const double q[4], double R[3][3]) {
  double w = q[0], x = q[1], y = q[2], z = q[3];
  R[0][0] = 1 - 2 * (y * y + z * z); R[0][1] = 2 * (x * y - w * z); R[0][2] = 2 * (x * z + w * y);
  R[1][0] = 2 * (x * y + w * z); R[1][1] = 1 - 2 * (x * x + z * z); R[1][2] = 2 * (y * z - w * x);
  R[2][0] = 2 * (x * z - w * y); R[2][1] = 2 * (y * z + w * x); R[2][2] = 1 - 2 * (x * x + y * y);
}

static double safe_atan2(double y, double x) { return (x == 0.0 && y == 0.0) ? 0.0 : atan2(y, x); }

/* (yaw, pitch, roll) of R (gpg.quadrotor.frames.euler_from_R) */
static void euler_from_R(double R[3][3], double e[3]) {
  double cp = hypot(R[0][0], R[1][0]);
  e[1] = safe_atan2(-R[2][0], cp);
  if (cp < 1e-12) { e[0] = safe_atan2(-R[0][1], R[1][1]); e[2] = 0.0; }
  else { e[0] = safe_atan2(R[1][0], R[0][0]); e[2] = safe_atan2(R[2][1], R[2][2]); }
}

static void cross(const double a[3], const double b[3], double c[3]) {
  c[0] = a[1] * b[2] - a[2] * b[1]; c[1] = a[2] * b[0] - a[0] * b[2]; c[2] = a[0] * b[1] - a[1] * b[0];
}

static double clip(double x, double lo, double hi) { return x < lo ? lo : x > hi ? hi : x; }

/* the minimum-jerk reference at t: position, velocity, acceleration and yaw */
static void reference(double t, double p[3], double v[3], double a[3], double *yaw) {
  int n_legs = N_WAYPOINTS - 1, leg, i, moving;
  double tau = (t - START_TIME) / LEG_TIME, s, pos, vel, acc, prev, turn, u, d;
  leg = (int)clip(floor(tau), 0, n_legs - 1);
  s = clip(tau - leg, 0.0, 1.0);
  if (tau < 0) s = 0.0;
  pos = 10 * pow(s, 3) - 15 * pow(s, 4) + 6 * pow(s, 5);
  vel = (30 * s * s - 60 * pow(s, 3) + 30 * pow(s, 4)) / LEG_TIME;
  acc = (60 * s - 180 * s * s + 120 * pow(s, 3)) / (LEG_TIME * LEG_TIME);
  moving = tau > 0 && tau < n_legs;
  for (i = 0; i < 3; i++) {
    d = WAYPOINTS[leg + 1][i] - WAYPOINTS[leg][i];
    p[i] = WAYPOINTS[leg][i] + pos * d;
    v[i] = moving ? vel * d : 0.0;
    a[i] = moving ? acc * d : 0.0;
  }
  prev = leg == 0 ? YAW0 : YAWS[leg - 1];
  turn = atan2(sin(YAWS[leg] - prev), cos(YAWS[leg] - prev));
  u = clip(s / TURN_FRACTION, 0.0, 1.0);
  *yaw = prev + turn * (10 * pow(u, 3) - 15 * pow(u, 4) + 6 * pow(u, 5));
}

/* rotor speeds (rpm) for collective thrust and moment; yaw yields first at the limits */
static void mix(double thrust, const double tau[3], double rpm[4]) {
  double lo = RPM_MIN * RPM_MIN, hi = RPM_MAX * RPM_MAX, base[4], u[4] = {thrust, tau[0], tau[1], 0};
  double t_lo = -INFINITY, t_hi = INFINITY, a, b, tz, r2, c;
  int i, j;
  for (i = 0; i < 4; i++) {
    base[i] = 0.0;
    for (j = 0; j < 4; j++) base[i] += ALLOC_INV[i][j] * u[j];
  }
  for (i = 0; i < 4; i++) {
    c = ALLOC_INV[i][3];
    if (fabs(c) > 0) {
      a = (lo - base[i]) / c; b = (hi - base[i]) / c;
      t_lo = fmax(t_lo, fmin(a, b)); t_hi = fmin(t_hi, fmax(a, b));
    }
  }
  tz = clip(tau[2], fmin(t_lo, 0.0), fmax(t_hi, 0.0));
  for (i = 0; i < 4; i++) {
    r2 = clip(base[i] + tz * ALLOC_INV[i][3], lo, hi);
    rpm[i] = sqrt(fmax(r2, 1e-6));
  }
}

/* the geometric controller: rotor speed commands for state s and the reference at t */
static void control(const State *s, double t, double cmd[4]) {
  double R[3][3], rp[3], rv[3], ra[3], yaw, F[3], up, hmax, hn, zb[3], xc[3], yb[3], xb[3];
  double Rd[3][3], M[3][3], eR[3], tau[3], Jw[3], wxJw[3], thrust = 0.0, n;
  int i, j, k;
  quat_to_R(s->q, R);
  reference(t, rp, rv, ra, &yaw);
  for (i = 0; i < 3; i++) F[i] = MASS * ra[i] - KP[i] * (s->p[i] - rp[i]) - KV[i] * (s->v[i] - rv[i]);
  F[2] -= MASS * GRAVITY;
  up = fmin(F[2], -0.2 * MASS * GRAVITY);
  hmax = -up * tan(MAX_TILT);
  hn = sqrt(F[0] * F[0] + F[1] * F[1] + 1e-12);
  F[0] *= fmin(1.0, hmax / hn); F[1] *= fmin(1.0, hmax / hn); F[2] = up;
  n = sqrt(F[0] * F[0] + F[1] * F[1] + F[2] * F[2]);
  for (i = 0; i < 3; i++) zb[i] = -F[i] / n;
  xc[0] = cos(yaw); xc[1] = sin(yaw); xc[2] = 0.0;
  cross(zb, xc, yb);
  n = sqrt(yb[0] * yb[0] + yb[1] * yb[1] + yb[2] * yb[2]);
  for (i = 0; i < 3; i++) yb[i] /= n;
  cross(yb, zb, xb);
  for (i = 0; i < 3; i++) { Rd[i][0] = xb[i]; Rd[i][1] = yb[i]; Rd[i][2] = zb[i]; }
  for (i = 0; i < 3; i++) thrust -= F[i] * R[i][2];
  thrust = fmax(thrust, 0.0);
  /* e_R = vee(Rd^T R - R^T Rd) / 2 */
  for (i = 0; i < 3; i++)
    for (j = 0; j < 3; j++) {
      M[i][j] = 0.0;
      for (k = 0; k < 3; k++) M[i][j] += Rd[k][i] * R[k][j] - R[k][i] * Rd[k][j];
    }
  eR[0] = 0.5 * M[2][1]; eR[1] = 0.5 * M[0][2]; eR[2] = 0.5 * M[1][0];
  for (i = 0; i < 3; i++) Jw[i] = INERTIA[i] * s->w[i];
  cross(s->w, Jw, wxJw);
  for (i = 0; i < 3; i++) tau[i] = -KR[i] * eR[i] - KW[i] * s->w[i] + wxJw[i];
  mix(thrust, tau, cmd);
}

/* d/dt of the state under the world-frame force and torque */
static void derivatives(const State *s, const double cmd[4], const double f[3], const double tq[3],
                        State *d) {
  double R[3][3], tb[3], Jw[3], wxJw[3];
  const double *q = s->q, *w = s->w;
  int i, j;
  quat_to_R(s->q, R);
  for (i = 0; i < 3; i++) { d->p[i] = s->v[i]; d->v[i] = f[i] / MASS; }
  d->v[2] += GRAVITY;
  for (i = 0; i < 3; i++) { tb[i] = 0.0; for (j = 0; j < 3; j++) tb[i] += R[j][i] * tq[j]; }
  for (i = 0; i < 3; i++) Jw[i] = INERTIA[i] * w[i];
  cross(w, Jw, wxJw);
  for (i = 0; i < 3; i++) d->w[i] = (tb[i] - wxJw[i]) / INERTIA[i];
  d->q[0] = 0.5 * (-q[1] * w[0] - q[2] * w[1] - q[3] * w[2]);
  d->q[1] = 0.5 * (q[0] * w[0] + q[2] * w[2] - q[3] * w[1]);
  d->q[2] = 0.5 * (q[0] * w[1] - q[1] * w[2] + q[3] * w[0]);
  d->q[3] = 0.5 * (q[0] * w[2] + q[1] * w[1] - q[2] * w[0]);
  for (i = 0; i < 4; i++)
    d->rpm[i] = MOTOR_TAU > 0 ? (clip(cmd[i], RPM_MIN, RPM_MAX) - s->rpm[i]) / MOTOR_TAU : 0.0;
}

static void axpy(const State *x, const State *k, double h, State *out) {
  const double *a = (const double *)x, *b = (const double *)k;
  double *o = (double *)out;
  int i;
  for (i = 0; i < 17; i++) o[i] = a[i] + h * b[i];
}

int main(void) {
  State s = {{0}}, k1, k2, k3, k4, tmp;
  double R[3][3], euler[3], wind[3], vair[3], f[3], tq[3], levels[64], cmd[4], t, n;
  double *x, *a, *b, *c, *d;
  int step, i, ok;
  for (i = 0; i < 3; i++) s.p[i] = P0[i];
  for (i = 0; i < 4; i++) { s.q[i] = Q0[i]; s.rpm[i] = RPM0[i]; }
  for (step = 0; step < N_STEPS; step++) {
    t = step * DT;
    control(&s, t, cmd);
    quat_to_R(s.q, R);
    euler_from_R(R, euler);
    for (i = 0; i < 3; i++) {
      wind[i] = WIND_MEAN[i] + WIND_GUST[i] * sin(2 * 3.141592653589793 * t / GUST_PERIOD + GUST_PHASE);
      vair[i] = s.v[i] - wind[i];
    }
    ok = AERO(s.rpm, euler, vair, f, tq, levels);
    printf("%.17g,%.17g,%.17g,%.17g,%.17g,%.17g,%.17g,%.17g,%.17g,%.17g,%.17g,%d\n", t, s.p[0],
           s.p[1], s.p[2], s.v[0], s.v[1], s.v[2], s.rpm[0], s.rpm[1], s.rpm[2], s.rpm[3], ok);
    derivatives(&s, cmd, f, tq, &k1);
    axpy(&s, &k1, DT / 2, &tmp); derivatives(&tmp, cmd, f, tq, &k2);
    axpy(&s, &k2, DT / 2, &tmp); derivatives(&tmp, cmd, f, tq, &k3);
    axpy(&s, &k3, DT, &tmp); derivatives(&tmp, cmd, f, tq, &k4);
    x = (double *)&s; a = (double *)&k1; b = (double *)&k2; c = (double *)&k3; d = (double *)&k4;
    for (i = 0; i < 17; i++) x[i] += DT / 6 * (a[i] + 2 * b[i] + 2 * c[i] + d[i]);
    n = sqrt(s.q[0] * s.q[0] + s.q[1] * s.q[1] + s.q[2] * s.q[2] + s.q[3] * s.q[3]);
    for (i = 0; i < 4; i++) s.q[i] /= n;
    if (!(MOTOR_TAU > 0)) for (i = 0; i < 4; i++) s.rpm[i] = clip(cmd[i], RPM_MIN, RPM_MAX);
  }
  return 0;
}
