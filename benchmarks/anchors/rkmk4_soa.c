/* The structure-of-arrays throughput anchor of issue 24, as given, plus one
   exported entry point (rkmk4_soa_run) so that benchmarks/native.py can call it
   through ctypes on the benchmark's own bodies and compare the attitudes.
   benchmarks/native.py builds it as a shared library with the line below plus
   -shared -fPIC; the standalone program (main) still builds as before. */
/* Throughput anchor: the same RKMK4 as lierk's (momentum-state free body, dexpinv to ad^2, Rodrigues exp),
   structure of arrays, blocks of 64 bodies held in L1 for all steps, SIMD across bodies, OpenMP across blocks.
   gcc -O3 -march=native -fno-math-errno -fopenmp rkmk4_soa.c -lm */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <omp.h>
#define BLK 64
static void block(int n, const double *Ii, const double *w0, double h, int steps, double *R) {
  double m0[BLK], m1[BLK], m2[BLK], r[9][BLK];
  for (int b = 0; b < n; b++) {
    m0[b] = w0[3*b] / Ii[0]; m1[b] = w0[3*b+1] / Ii[4]; m2[b] = w0[3*b+2] / Ii[8];  /* diagonal inertia here */
    for (int k = 0; k < 9; k++) r[k][b] = (k % 4 == 0);
  }
  const double hh = 0.5*h, h6 = h/6.0;
  for (int s = 0; s < steps; s++) {
    #pragma omp simd
    for (int b = 0; b < n; b++) {
      const double I0 = Ii[0], I1 = Ii[4], I2 = Ii[8];
      double y0 = m0[b], y1 = m1[b], y2 = m2[b];
#define STAGE(Y0,Y1,Y2,U0,U1,U2,K0,K1,K2,D0,D1,D2) { double w0_=I0*(Y0), w1_=I1*(Y1), w2_=I2*(Y2); \
        D0=(Y1)*w2_-(Y2)*w1_; D1=(Y2)*w0_-(Y0)*w2_; D2=(Y0)*w1_-(Y1)*w0_; \
        double a0=(U1)*w2_-(U2)*w1_, a1=(U2)*w0_-(U0)*w2_, a2=(U0)*w1_-(U1)*w0_; \
        double b0=(U1)*a2-(U2)*a1, b1=(U2)*a0-(U0)*a2, b2=(U0)*a1-(U1)*a0; \
        K0=w0_+0.5*a0+b0*(1.0/12); K1=w1_+0.5*a1+b1*(1.0/12); K2=w2_+0.5*a2+b2*(1.0/12); }
      double k10,k11,k12,d10,d11,d12,k20,k21,k22,d20,d21,d22,k30,k31,k32,d30,d31,d32,k40,k41,k42,d40,d41,d42;
      STAGE(y0,y1,y2,0.0,0.0,0.0,k10,k11,k12,d10,d11,d12)
      STAGE(y0+hh*d10,y1+hh*d11,y2+hh*d12,hh*k10,hh*k11,hh*k12,k20,k21,k22,d20,d21,d22)
      STAGE(y0+hh*d20,y1+hh*d21,y2+hh*d22,hh*k20,hh*k21,hh*k22,k30,k31,k32,d30,d31,d32)
      STAGE(y0+h*d30,y1+h*d31,y2+h*d32,h*k30,h*k31,h*k32,k40,k41,k42,d40,d41,d42)
      double U0 = h6*(k10+2*k20+2*k30+k40), U1 = h6*(k11+2*k21+2*k31+k41), U2 = h6*(k12+2*k22+2*k32+k42);
      m0[b] = y0 + h6*(d10+2*d20+2*d30+d40); m1[b] = y1 + h6*(d11+2*d21+2*d31+d41); m2[b] = y2 + h6*(d12+2*d22+2*d32+d42);
      double x = U0*U0 + U1*U1 + U2*U2, th = sqrt(x) + 1e-300;
      /* sin, cos of theta/2 by Taylor polynomials (exact to rounding for theta/2 < 0.5; per-step angles here are ~0.03) */
      double z = 0.5*th, z2 = z*z;
      double sn = z*(1 - z2/6*(1 - z2/20*(1 - z2/42*(1 - z2/72*(1 - z2/110*(1 - z2/156))))));
      double cs = 1 - z2/2*(1 - z2/12*(1 - z2/30*(1 - z2/56*(1 - z2/90*(1 - z2/132)))));
      double A = 2*sn*cs/th, B = 2*sn*sn/(th*th);
      double cc = 1 - B*x;
      double e0 = cc + B*U0*U0, e1 = B*U0*U1 - A*U2, e2 = B*U0*U2 + A*U1, e3 = B*U0*U1 + A*U2, e4 = cc + B*U1*U1,
             e5 = B*U1*U2 - A*U0, e6 = B*U0*U2 - A*U1, e7 = B*U1*U2 + A*U0, e8 = cc + B*U2*U2;
      double q0, q1, q2;
      q0 = r[0][b]; q1 = r[1][b]; q2 = r[2][b];
      r[0][b] = q0*e0 + q1*e3 + q2*e6; r[1][b] = q0*e1 + q1*e4 + q2*e7; r[2][b] = q0*e2 + q1*e5 + q2*e8;
      q0 = r[3][b]; q1 = r[4][b]; q2 = r[5][b];
      r[3][b] = q0*e0 + q1*e3 + q2*e6; r[4][b] = q0*e1 + q1*e4 + q2*e7; r[5][b] = q0*e2 + q1*e5 + q2*e8;
      q0 = r[6][b]; q1 = r[7][b]; q2 = r[8][b];
      r[6][b] = q0*e0 + q1*e3 + q2*e6; r[7][b] = q0*e1 + q1*e4 + q2*e7; r[8][b] = q0*e2 + q1*e5 + q2*e8;
    }
  }
  for (int b = 0; b < n; b++) for (int k = 0; k < 9; k++) R[9*b + k] = r[k][b];
}
/* R (B, 3, 3) row-major after `steps` steps of h from R0 = I, for omega0 (B, 3) (rad/s)
   and Ii the (3, 3) inverse inertia (diagonal: only Ii[0], Ii[4], Ii[8] are read). */
void rkmk4_soa_run(int B, const double *Ii, const double *w, double h, int steps, int threads, double *R) {
  omp_set_num_threads(threads);
  #pragma omp parallel for schedule(static)
  for (int b0 = 0; b0 < B; b0 += BLK) block(B - b0 < BLK ? B - b0 : BLK, Ii, w + 3*b0, h, steps, R + 9*b0);
}
int main(int argc, char **argv) {
  int B = argc > 1 ? atoi(argv[1]) : 10000, steps = argc > 2 ? atoi(argv[2]) : 1000;
  double Ii[9] = {1/0.000105, 0, 0, 0, 1/0.000211, 0, 0, 0, 1/0.000126};  /* inverse of a diagonal inertia */
  double *w = malloc(sizeof(double)*3*B), *R = malloc(sizeof(double)*9*B);
  for (int b = 0; b < B; b++) { w[3*b] = 1.0 + 1e-4*b/B; w[3*b+1] = 0.05; w[3*b+2] = 0.3; }
  double best = 1e30;
  for (int rep = 0; rep < 5; rep++) {
    double t = omp_get_wtime();
    #pragma omp parallel for schedule(static)
    for (int b0 = 0; b0 < B; b0 += BLK) block(B - b0 < BLK ? B - b0 : BLK, Ii, w + 3*b0, 0.01, steps, R + 9*b0);
    t = omp_get_wtime() - t; if (t < best) best = t;
  }
  printf("C SoA RKMK4, %d threads, batch %d, %d steps: %.3e body-steps/s (R[0]=%.6f)\n", omp_get_max_threads(), B, steps, B*(double)steps/best, R[0]);
  return 0;
}
