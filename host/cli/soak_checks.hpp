// The pass/fail rules of `magvec soak` (cmd_soak.cpp), as pure functions so the tests can feed
// them values that must fail (tests/host/cli/soak_test.cpp).
//
// Drift. Each interval's mean error of E, N, U and |h| against the simulator's true field is
// compared with the first interval's: |mean_i - mean_0| <= kDriftSigmas * sqrt(se_i^2 + se_0^2),
// se = sd / sqrt(n_eff). n_eff is the number of independent errors among the n samples:
//   |h|:   the magnetometer noise is drawn per sample, n_eff = n;
//   E/N/U: dominated by the INS attitude noise, drawn once per INS epoch and interpolated between
//          the two epochs that bracket a sample. The mean then weighs every epoch once
//          (var = sigma^2 / N_epochs) while a sample's variance is sigma^2 (w^2 + (1-w)^2),
//          2/3 sigma^2 on average, so n_eff = 2/3 N_epochs = 2/3 n ins_rate / mag_rate.
// 5 sigma: about 100 comparisons in a 24-hour run, a false alarm about once in 10^4 runs.
//
// Memory. VmRSS at the end of every interval; after the first interval (start-up, page faults of
// the first pass through every code path) it may not grow by more than kRssSlackKiB.
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <vector>

#include "stats.hpp"

namespace magvec::host::cli {

inline constexpr double kDriftSigmas = 5.0;
inline constexpr std::int64_t kRssSlackKiB = 1024;

// Running mean and spread of an error (Welford: no cancellation over 10^8 samples).
using ErrorStats = Stats;

// Error components: East, North, Up, |h|.
inline constexpr std::size_t kComponents = 4;
inline constexpr const char* kComponentNames[kComponents] = {"E", "N", "U", "|h|"};

struct IntervalStats {
  ErrorStats err[kComponents];
  std::int64_t rss_kib{-1};  // VmRSS at the end of the interval (-1: not read)
};

// Standard error of a mean whose n samples hold n * eff_fraction independent errors.
inline double standard_error(const ErrorStats& s, double eff_fraction) noexcept {
  const double n_eff = static_cast<double>(s.count()) * eff_fraction;
  return n_eff >= 1 ? s.sd() / std::sqrt(n_eff) : std::numeric_limits<double>::infinity();
}

// Independent fraction of the samples per component (see the top): E/N/U from the INS rate.
inline double eff_fraction(std::size_t component, double mag_rate_hz, double ins_rate_hz) noexcept {
  if (component == 3) return 1.0;
  const double f = 2.0 / 3.0 * ins_rate_hz / mag_rate_hz;
  return f < 1.0 ? f : 1.0;
}

struct DriftCheck {
  std::size_t interval{0};
  std::size_t component{0};
  double diff_nT{0};   // mean_i - mean_0
  double bound_nT{0};  // kDriftSigmas * sqrt(se_i^2 + se_0^2)
  bool ok() const noexcept { return std::fabs(diff_nT) <= bound_nT; }
};

// Every interval after the first against the first. Intervals without scored samples fail (a
// run that scores nothing must not pass).
inline std::vector<DriftCheck> drift_checks(const std::vector<IntervalStats>& intervals,
                                            double mag_rate_hz, double ins_rate_hz) {
  std::vector<DriftCheck> v;
  if (intervals.empty()) return v;
  const IntervalStats& ref = intervals.front();
  for (std::size_t i = 1; i < intervals.size(); ++i) {
    for (std::size_t c = 0; c < kComponents; ++c) {
      const double f = eff_fraction(c, mag_rate_hz, ins_rate_hz);
      const ErrorStats& a = intervals[i].err[c];
      const ErrorStats& b = ref.err[c];
      DriftCheck d;
      d.interval = i;
      d.component = c;
      d.diff_nT = a.mean() - b.mean();
      const double se_a = standard_error(a, f);
      const double se_b = standard_error(b, f);
      d.bound_nT = kDriftSigmas * std::sqrt(se_a * se_a + se_b * se_b);
      if (a.count() < 2 || b.count() < 2) d.bound_nT = -1;  // nothing scored: fails
      v.push_back(d);
    }
  }
  return v;
}

struct RssCheck {
  std::int64_t first_kib{-1};  // end of the first interval
  std::int64_t last_kib{-1};   // end of the run
  std::int64_t growth_kib{0};  // largest later value minus first_kib
  std::int64_t slack_kib{kRssSlackKiB};
  bool ok() const noexcept { return first_kib >= 0 && growth_kib <= slack_kib; }
};

// rss_kib: one value per interval end (a value < 0 was not read and fails the check).
inline RssCheck rss_check(const std::vector<std::int64_t>& rss_kib,
                          std::int64_t slack_kib = kRssSlackKiB) noexcept {
  RssCheck r;
  r.slack_kib = slack_kib;
  if (rss_kib.empty()) return r;
  r.first_kib = rss_kib.front();
  r.last_kib = rss_kib.back();
  for (std::int64_t v : rss_kib) {
    if (v < 0) {
      r.first_kib = -1;
      return r;
    }
    if (v - r.first_kib > r.growth_kib) r.growth_kib = v - r.first_kib;
  }
  return r;
}

}  // namespace magvec::host::cli
