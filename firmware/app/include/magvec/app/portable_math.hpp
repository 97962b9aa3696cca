// Portable double-precision elementary functions (the M7 double image and its host twin
// must agree bit for bit). newlib (fdlibm) and glibc compute sin, cos, atan2, asin, log, ... with
// different algorithms, neither correctly rounded in general, so their results may differ in the
// last bit; one such bit in the simulator or the calibrator can flip a rounding downstream (an
// ADC code, a gate decision) and the two runs then diverge. With these the image and its twin do
// not depend on the C library at all. (Measured on the app scenario: once the simulator's noise
// draws were sequenced, the runs also matched with the two C libraries; this removes the latent
// dependence rather than a difference observed in that run.)
// These implementations use only IEEE-754 basic operations (+ - * / and sqrt, correctly rounded
// on every target) in a fixed order, so every IEEE double target without FMA contraction
// (-ffp-contract=off) computes the same bits. Methods (after fdlibm, Sun Microsystems 1993):
// Cody-Waite reduction by pi/2 in three parts and Taylor polynomials on [-pi/4, pi/4] (sin, cos);
// reduction to |t| <= 7/16 with atan(0.5), atan(1), atan(1.5), atan(inf) and the Taylor series
// (atan, atan2, asin and acos through atan2); log(1+f) = f - (f^2/2 - s (f^2/2 + R(s^2))),
// s = f / (2 + f) (log); exp by reduction with ln 2 in two parts and a Taylor polynomial.
// Accuracy: within a few ulp of the correctly rounded result (tests/firmware/app/portable_math_test
// checks <= 2 ulp against glibc on random arguments). Not optimised for speed: the simulator and
// the calibrator's rare solves use them; the per-sample path of the float image uses none.
// The image links and its host twin links route the C library's double functions here with
// `--wrap` (firmware/app/CMakeLists.txt, src/portable_math.cpp).
#pragma once

namespace magvec::app::portable {

double sin(double x) noexcept;
double cos(double x) noexcept;
void sincos(double x, double* s, double* c) noexcept;
double atan(double x) noexcept;
double atan2(double y, double x) noexcept;
double asin(double x) noexcept;
double acos(double x) noexcept;
double log(double x) noexcept;
double exp(double x) noexcept;

}  // namespace magvec::app::portable
