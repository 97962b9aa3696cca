// Real recorded data: BROAD benchmark trial 02 (Laidig et al., Data 6(7):72, 2021, CC BY 4.0) —
// a MEMS magnetometer rotated slowly by hand with optical motion-capture attitude, indoors.
// The file lives in ../shared/data/real and is not part of a user's checkout: without it the tests
// skip. There is no scalar reference, so the fits run on |h| = median |m| (scale is then relative)
// and are judged against the resting noise floor and by the spread of the ENU components.
#include <gtest/gtest.h>

#include <algorithm>
#include <filesystem>
#include <memory>
#include <vector>

#include "magvec/core/batch_calibrator.hpp"
#include "magvec/host/io/csv.hpp"

namespace magvec {
namespace {

const std::string kFile = std::string(MAGVEC_SHARED_DIR) + "/data/real/broad_02_slow_rotation.csv";

struct Row {
  core::Vec3<double> m;
  core::Mat3<double> r_bn;
};

// SD of |m| while the sensor rests (movement = 0): the magnetometer's own noise floor.
double static_intensity_sd() {
  host::io::CsvReader reader(kFile);
  const auto movement = reader.column_index("movement");
  std::vector<double> mags;
  host::io::CsvRecord rec;
  while (reader.next(&rec)) {
    if (!rec.dropout && movement && reader.value(*movement) == 0.0) mags.push_back(rec.m_nT.norm());
  }
  double mean = 0;
  for (double x : mags)
    mean += x / static_cast<double>(mags.size());
  double ss = 0;
  for (double x : mags)
    ss += (x - mean) * (x - mean);
  return std::sqrt(ss / static_cast<double>(mags.size() - 1));
}

std::vector<Row> load_moving_rows(std::size_t decimate) {
  host::io::CsvReader reader(kFile);
  const auto movement = reader.column_index("movement");
  std::vector<Row> rows;
  host::io::CsvRecord rec;
  std::size_t i = 0;
  while (reader.next(&rec)) {
    if (rec.dropout || !rec.r_bn || !movement || reader.value(*movement) != 1.0) continue;
    if (i++ % decimate != 0) continue;
    rows.push_back({rec.m_nT, *rec.r_bn});
  }
  return rows;
}

double sd(const std::vector<double>& v) {
  double mean = 0;
  for (double x : v)
    mean += x / static_cast<double>(v.size());
  double s = 0;
  for (double x : v)
    s += (x - mean) * (x - mean);
  return std::sqrt(s / static_cast<double>(v.size() - 1));
}

TEST(BroadRealData, JointCalibrationShrinksIntensityAndComponentSpread) {
  if (!std::filesystem::exists(kFile)) GTEST_SKIP() << "real data not present: " << kFile;
  const std::vector<Row> rows = load_moving_rows(8);
  ASSERT_GT(rows.size(), 2000u);
  std::vector<double> mags;
  for (const Row& r : rows)
    mags.push_back(r.m.norm());
  std::nth_element(mags.begin(), mags.begin() + static_cast<long>(mags.size() / 2), mags.end());
  const double f = mags[mags.size() / 2];

  core::BatchConfig<double> cfg;
  cfg.field_nT = f;
  cfg.mag_noise_nT = 300;        // MEMS magnetometer: a few hundred nT per sample
  cfg.attitude_noise_deg = 0.5;  // optical attitude vs IMU frame, hand motion
  cfg.max_intensity_rms_nT = 2000;
  cfg.max_chi2_per_dof = 100;
  auto cal = std::make_unique<core::BatchCalibrator<double, 8192>>(cfg);
  for (const Row& r : rows)
    cal->add_sample(r.m, f, r.r_bn);
  // The joint fit (ellipsoid, then Rm with h_n; ERRATA 000-5). The one-step refinement does not
  // converge on this recording within its iteration limit (MEMS noise far from the model's
  // white-noise assumption), and says so with its verdict rather than returning a poor fit.
  const core::BatchResult<double> res = cal->solve(core::BatchMethod::kJoint);
  ASSERT_TRUE(res.ok()) << core::verdict_name(res.verdict);

  // Before: raw readings rotated to ENU; after: calibrated.
  const core::Mat3<double> rm_t = res.model.rm_matrix().transpose();
  std::vector<double> f_before, f_after, enu_before[3], enu_after[3];
  for (const Row& r : rows) {
    const core::Vec3<double> h_s = res.model.w * (r.m - res.model.o);
    f_before.push_back(r.m.norm());
    f_after.push_back(h_s.norm());
    const core::Vec3<double> nb = r.r_bn.transpose() * r.m;
    const core::Vec3<double> na = r.r_bn.transpose() * (rm_t * h_s);
    for (int k = 0; k < 3; ++k) {
      enu_before[k].push_back(nb(k));
      enu_after[k].push_back(na(k));
    }
  }
  const double f_sd_before = sd(f_before), f_sd_after = sd(f_after);
  RecordProperty("intensity_sd_before_nT", std::to_string(f_sd_before));
  RecordProperty("intensity_sd_after_nT", std::to_string(f_sd_after));
  // The raw MEMS data are noise-dominated (about 680 nT per sample at rest): calibration can only
  // remove the systematic part, so the calibrated intensity spread must come down to the resting
  // noise floor, and every ENU component must get tighter (the lab field itself varies as the
  // sensor is carried around, so the components have no known floor).
  const double floor = static_intensity_sd();
  std::cout << "resting noise floor of |m|: " << floor << " nT\n";
  EXPECT_LT(f_sd_after, f_sd_before);
  EXPECT_LT(f_sd_after, 1.05 * floor);
  for (int k = 0; k < 3; ++k) {
    const double b = sd(enu_before[k]), a = sd(enu_after[k]);
    std::cout << "ENU[" << k << "] spread " << b << " -> " << a << " nT\n";
    EXPECT_LT(a, b) << "component " << k;
  }
  std::cout << "intensity spread " << f_sd_before << " -> " << f_sd_after << " nT over "
            << rows.size() << " samples; misalignment deg " << res.li.rm_rad.transpose() * 57.29578
            << "\n";
}

}  // namespace
}  // namespace magvec
