// Portable double elementary functions; see portable_math.hpp for why and how. The constants in
// hex are the splits of pi/2, pi and ln 2 into a head with trailing zero bits (so k * head is exact
// for the k used) and the rounded remainder, generated with mpmath at 300 bits; the polynomial
// coefficients are the Taylor coefficients, exact rationals rounded once by the compiler.
#include "magvec/app/portable_math.hpp"

#include <array>
#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>

namespace magvec::app::portable {
namespace {

constexpr double kPio2Hi1 = 0x1.921fb54400000p+0;   // pi/2, first 33 bits
constexpr double kPio2Hi2 = 0x1.0b4611a600000p-34;  // next 33 bits
constexpr double kPio2Lo = 0x1.3198a2e037073p-69;   // the rest
constexpr double kInvPio2 = 0x1.45f306dc9c883p-1;   // 2/pi
constexpr double kPi = 0x1.921fb54442d18p+1;
constexpr double kPiLo = 0x1.1a62633145c07p-53;
constexpr double kPio2 = 0x1.921fb54442d18p+0;
constexpr double kPio2Lo1 = 0x1.1a62633145c07p-54;
constexpr double kPio4 = 0x1.921fb54442d18p-1;
constexpr double kLn2Hi = 0x1.62e42fee00000p-1;  // ln 2, first 32 bits
constexpr double kLn2Lo = 0x1.a39ef35793c76p-33;
constexpr double kInvLn2 = 0x1.71547652b82fep+0;
constexpr double kSqrt2 = 0x1.6a09e667f3bcdp+0;
constexpr double kTwoPi = 0x1.921fb54442d18p+2;
// Above this |x| the product k * kPio2Hi1 would no longer be exact (k >= 2^20).
constexpr double kCodyWaiteLimit = 0x1.921fb5p+20;

constexpr double factorial(int n) {
  double f = 1.0;
  for (int i = 2; i <= n; ++i)
    f *= i;  // exact up to 22!: the odd part stays below 2^53
  return f;
}

// sin(r) = r + r^3 (S3 + r^2 (S5 + ... + r^2 S19)), |r| <= pi/4: the first omitted term,
// (pi/4)^21 / 21!, is below 1e-21 of r.
constexpr std::array<double, 9> kSinCoeff = {
    -1.0 / factorial(3),  1.0 / factorial(5),   -1.0 / factorial(7),
    1.0 / factorial(9),   -1.0 / factorial(11), 1.0 / factorial(13),
    -1.0 / factorial(15), 1.0 / factorial(17),  -1.0 / factorial(19)};
// cos(r) = 1 - r^2/2 + r^4 (C4 + r^2 (C6 + ... + r^2 C20)).
constexpr std::array<double, 9> kCosCoeff = {
    1.0 / factorial(4),   -1.0 / factorial(6),  1.0 / factorial(8),
    -1.0 / factorial(10), 1.0 / factorial(12),  -1.0 / factorial(14),
    1.0 / factorial(16),  -1.0 / factorial(18), 1.0 / factorial(20)};

template <std::size_t N>
double horner(const std::array<double, N>& c, double z) noexcept {
  double p = c[N - 1];
  for (std::size_t i = N - 1; i-- > 0;)
    p = c[i] + z * p;
  return p;
}

double sin_kernel(double r) noexcept {
  if (std::fabs(r) < 0x1p-27) return r;  // r^3/6 is below half an ulp (and sin(-0) = -0)
  const double z = r * r;
  return r + r * (z * horner(kSinCoeff, z));
}

double cos_kernel(double r) noexcept {
  const double z = r * r;
  const double hz = 0.5 * z;
  const double w = 1.0 - hz;
  // 1 - hz rounded, plus what the rounding lost, plus the tail (fdlibm's __kernel_cos).
  return w + (((1.0 - w) - hz) + z * z * horner(kCosCoeff, z));
}

// x = k pi/2 + r, |r| <= ~pi/4; returns k mod 4.
int reduce_pio2(double x, double* r) noexcept {
  if (std::fabs(x) >= kCodyWaiteLimit) {
    // Rare (the scenarios' angles are small): fmod is exact on every C library, but 2 pi in
    // double is not 2 pi, so the reduction loses |x| * 2.4e-16 / (2 pi) absolutely.
    x = std::fmod(x, kTwoPi);
  }
  const double kd = x * kInvPio2;
  const auto k = static_cast<std::int32_t>(kd >= 0 ? kd + 0.5 : kd - 0.5);
  const double fk = static_cast<double>(k);
  *r = ((x - fk * kPio2Hi1) - fk * kPio2Hi2) - fk * kPio2Lo;
  return static_cast<int>(static_cast<std::uint32_t>(k) & 3U);
}

// atan(t) for |t| <= 7/16: t + t (t^2 (A3 + t^2 (A5 + ...))), Taylor to t^45
// ((7/16)^47 / 47 < 1e-18 t).
constexpr std::array<double, 22> make_atan_coeff() {
  std::array<double, 22> c{};
  for (int k = 1; k <= 22; ++k)
    c[static_cast<std::size_t>(k - 1)] = (k % 2 == 0 ? 1.0 : -1.0) / (2 * k + 1);
  return c;
}
constexpr std::array<double, 22> kAtanCoeff = make_atan_coeff();

// atan(c) for c = 0.5, 1, 1.5, inf, as head + tail.
constexpr std::array<double, 4> kAtanHi = {0x1.dac670561bb4fp-2, 0x1.921fb54442d18p-1,
                                           0x1.f730bd281f69bp-1, 0x1.921fb54442d18p+0};
constexpr std::array<double, 4> kAtanLo = {0x1.a2b7f222f65e2p-56, 0x1.1a62633145c07p-55,
                                           0x1.007887af0cbbdp-56, 0x1.1a62633145c07p-54};

// log(1 + f) = f - (hfsq - s (hfsq + R(z))), s = f / (2 + f), z = s^2,
// R(z) = 2z/3 + 2z^2/5 + ... (to z^12: z <= 0.0295, the rest is below 1e-19 of the result).
constexpr std::array<double, 12> make_log_coeff() {
  std::array<double, 12> c{};
  for (int k = 1; k <= 12; ++k)
    c[static_cast<std::size_t>(k - 1)] = 2.0 / (2 * k + 1);
  return c;
}
constexpr std::array<double, 12> kLogCoeff = make_log_coeff();

// exp(r) - 1 - r = r^2 (E2 + r (E3 + ...)), |r| <= ln2/2: Taylor to r^16.
constexpr std::array<double, 15> make_exp_coeff() {
  std::array<double, 15> c{};
  for (int n = 2; n <= 16; ++n)
    c[static_cast<std::size_t>(n - 2)] = 1.0 / factorial(n);
  return c;
}
constexpr std::array<double, 15> kExpCoeff = make_exp_coeff();

// 2^e as a double, e in the normal range [-1022, 1023].
double pow2(int e) noexcept {
  return std::bit_cast<double>(static_cast<std::uint64_t>(e + 1023) << 52);
}

}  // namespace

double sin(double x) noexcept {
  if (!std::isfinite(x)) return x - x;  // NaN (inf - inf), NaN propagated
  double r = 0;
  switch (reduce_pio2(x, &r)) {
    case 0:
      return sin_kernel(r);
    case 1:
      return cos_kernel(r);
    case 2:
      return -sin_kernel(r);
    default:
      return -cos_kernel(r);
  }
}

double cos(double x) noexcept {
  if (!std::isfinite(x)) return x - x;
  double r = 0;
  switch (reduce_pio2(x, &r)) {
    case 0:
      return cos_kernel(r);
    case 1:
      return -sin_kernel(r);
    case 2:
      return -cos_kernel(r);
    default:
      return sin_kernel(r);
  }
}

void sincos(double x, double* s, double* c) noexcept {
  *s = sin(x);
  *c = cos(x);
}

double atan(double x) noexcept {
  if (std::isnan(x)) return x + x;
  const double ax = std::fabs(x);
  if (ax >= 0x1p66) return x > 0 ? kPio2 + kPio2Lo1 : -kPio2 - kPio2Lo1;
  int id = -1;
  double t = ax;
  if (ax < 0.4375) {
    if (ax < 0x1p-29) return x;  // atan(x) = x - x^3/3: the cube is below half an ulp
  } else if (ax < 0.6875) {
    id = 0;
    t = (2.0 * ax - 1.0) / (2.0 + ax);
  } else if (ax < 1.1875) {
    id = 1;
    t = (ax - 1.0) / (ax + 1.0);
  } else if (ax < 2.4375) {
    id = 2;
    t = (ax - 1.5) / (1.0 + 1.5 * ax);
  } else {
    id = 3;
    t = -1.0 / ax;
  }
  const double tail = t * (t * t * horner(kAtanCoeff, t * t));
  if (id < 0) return x >= 0 ? t + tail : -(t + tail);
  const auto i = static_cast<std::size_t>(id);
  const double z = kAtanHi[i] - ((-tail - kAtanLo[i]) - t);  // hi + lo + atan(t)
  return x >= 0 ? z : -z;
}

double atan2(double y, double x) noexcept {
  if (std::isnan(x) || std::isnan(y)) return x + y;
  const bool yneg = std::signbit(y);
  const bool xneg = std::signbit(x);
  if (y == 0) {
    if (!xneg) return y;                       // atan2(+-0, +x) = +-0
    return yneg ? -kPi - kPiLo : kPi + kPiLo;  // atan2(+-0, -x) = +-pi
  }
  if (x == 0) return yneg ? -kPio2 - kPio2Lo1 : kPio2 + kPio2Lo1;
  if (std::isinf(x)) {
    if (std::isinf(y)) {
      const double a = xneg ? 3.0 * kPio4 : kPio4;
      return yneg ? -a : a;
    }
    if (!xneg) return yneg ? -0.0 : 0.0;
    return yneg ? -kPi - kPiLo : kPi + kPiLo;
  }
  if (std::isinf(y)) return yneg ? -kPio2 - kPio2Lo1 : kPio2 + kPio2Lo1;

  const double q = std::fabs(y / x);
  double z = 0;
  if (std::isinf(q) || q > 0x1p60) {
    z = kPio2 + 0.5 * kPiLo;
  } else if (xneg && q < 0x1p-60) {
    z = 0.0;  // |y/x| tiny, x < 0: the result is pi up to an ulp
  } else {
    z = atan(q);
  }
  if (!xneg) return yneg ? -z : z;
  const double w = kPi - (z - kPiLo);
  return yneg ? -w : w;
}

double asin(double x) noexcept {
  if (std::isnan(x)) return x + x;
  if (std::fabs(x) > 1) return std::numeric_limits<double>::quiet_NaN();
  return atan2(x, std::sqrt((1.0 - x) * (1.0 + x)));
}

double acos(double x) noexcept {
  if (std::isnan(x)) return x + x;
  if (std::fabs(x) > 1) return std::numeric_limits<double>::quiet_NaN();
  return atan2(std::sqrt((1.0 - x) * (1.0 + x)), x);
}

double log(double x) noexcept {
  if (std::isnan(x)) return x + x;
  if (x < 0) return std::numeric_limits<double>::quiet_NaN();
  if (x == 0) return -std::numeric_limits<double>::infinity();
  if (std::isinf(x)) return x;
  int e = 0;
  if (x < std::numeric_limits<double>::min()) {  // subnormal: scale into the normal range
    x *= 0x1p54;
    e = -54;
  }
  const auto bits = std::bit_cast<std::uint64_t>(x);
  e += static_cast<int>((bits >> 52) & 0x7ffU) - 1023;
  double m = std::bit_cast<double>((bits & 0x000fffffffffffffULL) | 0x3ff0000000000000ULL);
  if (m > kSqrt2) {  // m in [sqrt(2)/2, sqrt(2)): |f| <= 0.414
    m *= 0.5;
    ++e;
  }
  const double f = m - 1.0;  // exact (Sterbenz)
  const double s = f / (2.0 + f);
  const double z = s * s;
  const double r = z * horner(kLogCoeff, z);
  const double hfsq = 0.5 * f * f;
  const double de = static_cast<double>(e);
  return de * kLn2Hi - ((hfsq - (s * (hfsq + r) + de * kLn2Lo)) - f);
}

double exp(double x) noexcept {
  if (std::isnan(x)) return x + x;
  if (x > 709.782712893384) return std::numeric_limits<double>::infinity();
  if (x < -745.1332191019412) return 0.0;
  if (std::fabs(x) < 0x1p-54) return 1.0 + x;
  const double kd = x * kInvLn2;
  const auto k = static_cast<int>(kd >= 0 ? kd + 0.5 : kd - 0.5);
  const double fk = static_cast<double>(k);
  const double hi = x - fk * kLn2Hi;  // exact: k * kLn2Hi has at most 43 bits
  const double lo = fk * kLn2Lo;
  const double r = hi - lo;
  const double y = 1.0 + (hi - (lo - r * r * horner(kExpCoeff, r)));
  // 2^k y, in two steps near the ends of the range (k up to 1024, down to -1075).
  if (k > 1000) return y * pow2(k - 1000) * pow2(1000);
  if (k < -1000) return y * pow2(k + 1000) * pow2(-1000);
  return y * pow2(k);
}

}  // namespace magvec::app::portable

// Link-time routing (`--wrap=<f>` on the image and host-twin links): every reference to the C
// library's double function <f> from the app's objects resolves to __wrap_<f>.
extern "C" {
double __wrap_sin(double x) noexcept;
double __wrap_cos(double x) noexcept;
void __wrap_sincos(double x, double* s, double* c) noexcept;
double __wrap_atan(double x) noexcept;
double __wrap_atan2(double y, double x) noexcept;
double __wrap_asin(double x) noexcept;
double __wrap_acos(double x) noexcept;
double __wrap_log(double x) noexcept;
double __wrap_exp(double x) noexcept;

double __wrap_sin(double x) noexcept {
  return magvec::app::portable::sin(x);
}
double __wrap_cos(double x) noexcept {
  return magvec::app::portable::cos(x);
}
void __wrap_sincos(double x, double* s, double* c) noexcept {
  magvec::app::portable::sincos(x, s, c);
}
double __wrap_atan(double x) noexcept {
  return magvec::app::portable::atan(x);
}
double __wrap_atan2(double y, double x) noexcept {
  return magvec::app::portable::atan2(y, x);
}
double __wrap_asin(double x) noexcept {
  return magvec::app::portable::asin(x);
}
double __wrap_acos(double x) noexcept {
  return magvec::app::portable::acos(x);
}
double __wrap_log(double x) noexcept {
  return magvec::app::portable::log(x);
}
double __wrap_exp(double x) noexcept {
  return magvec::app::portable::exp(x);
}
}
