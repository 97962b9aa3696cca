// The E/N/U accuracy floor of a record, from the simulator's TRUE attitude and field and the
// configured noise only (never from the loop's own buffered attitude): the error an ideal
// pipeline would still make with a perfect calibration and perfect time alignment.
//   - INS noise: the simulator adds white noise of SD ins_noise_deg to each Li Euler angle of
//     every INS epoch; the attitude at a time between two epochs is interpolated (slerp), so the
//     angle noise there has variance sigma^2 ((1 - f)^2 + f^2), f the fraction between the epochs.
//     Propagated to h_n = R_bn(e)^T h_b through the Jacobian with respect to (alpha, beta, gamma)
//     at the true angles (central differences).
//   - Magnetometer noise (SD per axis) through h_n = R_bn^T Rm^T W (m - o) of the true model.
#pragma once

#include <cmath>
#include <cstdint>

#include "magvec/core/frames.hpp"
#include "magvec/core/sensor_model.hpp"

namespace magvec::test {

struct EnuFloorAccumulator {
  double var_sum[3]{0, 0, 0};
  double err_sum_sq[3]{0, 0, 0};
  std::uint64_t n{0};

  // r_bn_true, h_n_true at the sample's time; f: interpolation fraction between INS epochs.
  void add(const core::Vec3<double>& h_n_out, const core::Mat3<double>& r_bn_true,
           const core::Vec3<double>& h_n_true, const core::SensorModel<double>& truth,
           double mag_noise_nT, double ins_noise_deg, double f) {
    const core::Vec3<double> h_b = r_bn_true * h_n_true;
    const core::LiEuler<double> e0 = core::li_from_r_bn(r_bn_true);
    core::Mat3<double> jac;
    constexpr double kStep = 1e-6;
    for (int j = 0; j < 3; ++j) {
      core::LiEuler<double> ep = e0, em = e0;
      double* pp = j == 0 ? &ep.alpha : (j == 1 ? &ep.beta : &ep.gamma);
      double* pm = j == 0 ? &em.alpha : (j == 1 ? &em.beta : &em.gamma);
      *pp += kStep;
      *pm -= kStep;
      jac.col(j) =
          (core::r_bn_from_li(ep).transpose() * h_b - core::r_bn_from_li(em).transpose() * h_b) /
          (2 * kStep);
    }
    const double s_ins = core::deg_to_rad(ins_noise_deg);
    const double w = (1 - f) * (1 - f) + f * f;
    const core::Mat3<double> m_to_n =
        r_bn_true.transpose() * truth.rm_matrix().transpose() * truth.w;
    for (int k = 0; k < 3; ++k) {
      var_sum[k] += s_ins * s_ins * w * jac.row(k).squaredNorm() +
                    mag_noise_nT * mag_noise_nT * m_to_n.row(k).squaredNorm();
      const double e = h_n_out(k) - h_n_true(k);
      err_sum_sq[k] += e * e;
    }
    ++n;
  }
  void merge(const EnuFloorAccumulator& o) {
    for (int k = 0; k < 3; ++k) {
      var_sum[k] += o.var_sum[k];
      err_sum_sq[k] += o.err_sum_sq[k];
    }
    n += o.n;
  }
  double floor(int k) const { return n ? std::sqrt(var_sum[k] / static_cast<double>(n)) : 0; }
  double error(int k) const { return n ? std::sqrt(err_sum_sq[k] / static_cast<double>(n)) : 0; }
};

// Fraction of t_s between the INS epochs (epochs at k / ins_rate_hz).
inline double epoch_fraction(double t_s, double ins_rate_hz) {
  const double x = t_s * ins_rate_hz;
  const double f = x - std::floor(x);
  return f < 1e-9 || f > 1 - 1e-9 ? 0.0 : f;
}

}  // namespace magvec::test
