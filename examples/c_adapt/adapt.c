/* adapt.c: a flight log's labels read from a CSV file, each predicted by the adapted model
 * before it is used, then used to update it: what a flight controller or an onboard computer
 * does with gpg's model at every label (gpg.flight.adapt, gpg.export.to_c).
 *
 * Build with the exported model (gpg.export.to_c(adapted, "build", name="model")):
 *   cc -O2 -std=c99 -I build -o adapt adapt.c build/model.c -lm
 * Run:
 *   ./adapt labels.csv > predictions.csv
 * labels.csv: a header line, then one label a line, 23 numbers separated by commas:
 *   t, rpm1..rpm4, yaw, pitch, roll, vx, vy, vz (air velocity, world), fx, fy, fz (N, world),
 *   tx, ty, tz (N*m), fvx, fvy, fvz, tvx, tvy, tvz (their noise variances)
 * predictions.csv: per label, t, the predicted force and torque (world) before the update,
 * their predictive variances, in_domain, and whether the update used the label.
 * The state is one fixed-size struct on the stack: nothing is allocated. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "model.h"

#define N_COLS 23

int main(int argc, char **argv) {
  FILE *in;
  char line[4096];
  double c[N_COLS], force[3], torque[3], levels[MODEL_N_LEVELS + 1];
  double variance[6 + MODEL_N_LEVELS];
  static model_online state; /* static: a bank's state is hundreds of kB */
  long n = 0;
  int i, ok, used;
  if (argc != 2) {
    fprintf(stderr, "usage: %s labels.csv\n", argv[0]);
    return 2;
  }
  in = fopen(argv[1], "r");
  if (!in) {
    perror(argv[1]);
    return 2;
  }
  model_online_init(&state);
  if (!fgets(line, sizeof line, in)) { /* the header */
    fprintf(stderr, "%s: empty file\n", argv[1]);
    fclose(in);
    return 2;
  }
  printf("t,fx,fy,fz,tx,ty,tz,var_fx,var_fy,var_fz,var_tx,var_ty,var_tz,in_domain,used\n");
  while (fgets(line, sizeof line, in)) {
    char *p = line, *end;
    for (i = 0; i < N_COLS; i++) {
      c[i] = strtod(p, &end);
      if (end == p) break;
      p = end;
      while (*p == ',' || *p == ' ') p++;
    }
    n++;
    if (i < N_COLS) {
      fprintf(stderr, "%s: line %ld has %d numbers, not %d\n", argv[1], n + 1, i, N_COLS);
      fclose(in);
      return 1;
    }
    /* predicted before the label is used (prequential), then the update */
    ok = model_online_predict(&state, c + 1, c + 5, c + 8, force, torque, levels, variance);
    used = model_online_update(&state, c[0], c + 1, c + 5, c + 8, c + 11, c + 14, c + 17, c + 20);
    printf("%.17g", c[0]);
    for (i = 0; i < 3; i++) printf(",%.17g", force[i]);
    for (i = 0; i < 3; i++) printf(",%.17g", torque[i]);
    for (i = 0; i < 6; i++) printf(",%.17g", variance[i]);
    printf(",%d,%d\n", ok, used);
  }
  fclose(in);
  return 0;
}
