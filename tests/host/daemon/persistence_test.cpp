// CalibrationStore (host/daemon persistence.hpp): magvecd's cal.json round trip, a missing file,
// a corrupt file refused and left byte for byte, a failed write keeping the previous file.
#include "magvec/host/daemon/persistence.hpp"

#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <sstream>

#include "magvec/host/daemon/daemon_error.hpp"

namespace magvec::host::daemon {
namespace {

class CalibrationStoreTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = std::filesystem::temp_directory_path() /
           ("magvec_store_test_" + std::to_string(::getpid()));
    std::filesystem::remove_all(dir_);
    std::filesystem::create_directories(dir_);
  }
  void TearDown() override { std::filesystem::remove_all(dir_); }
  static std::string read(const std::filesystem::path& p) {
    std::ifstream in(p, std::ios::binary);
    std::ostringstream os;
    os << in.rdbuf();
    return os.str();
  }
  static CalibrationStatus status(std::uint32_t cal_id) {
    CalibrationStatus st;
    st.calibrator = "li";
    st.cal_id = cal_id;
    st.validation_rms_nT = 0.25;
    st.active.w << 1.01, 0.002, -0.001, 0, 0.99, 0.003, 0, 0, 1.02;
    st.active.o = core::Vec3<double>(120.5, -33.25, 7.125);
    st.active.rm = core::Quat<double>(0.9999, 0.01, -0.005, 0.002).normalized();
    st.output = OutputQuality{false, 0.75, 12.5};
    return st;
  }
  std::filesystem::path dir_;
};

TEST_F(CalibrationStoreTest, NoFileStartsUncalibrated) {
  CalibrationStore s(dir_.string());
  EXPECT_EQ(s.path(), (dir_ / "cal.json").string());
  EXPECT_FALSE(s.load().present);
  EXPECT_FALSE(s.persisted().present);
}

TEST_F(CalibrationStoreTest, SavedCalibrationLoadsBack) {
  CalibrationStore s(dir_.string());
  std::string error;
  const CalibrationStatus st = status(3);
  ASSERT_TRUE(s.save(st, 0.012, "test", &error)) << error;
  EXPECT_TRUE(s.persisted().present);
  EXPECT_EQ(s.persisted().cal_id, 3u);
  CalibrationStore again(dir_.string());
  const PersistedCalibration p = again.load();
  ASSERT_TRUE(p.present);
  EXPECT_EQ(p.cal_id, 3u);
  EXPECT_DOUBLE_EQ(p.time_offset_s, 0.012);
  EXPECT_LT((p.model.w - st.active.w).norm(), 1e-12);
  EXPECT_LT((p.model.o - st.active.o).norm(), 1e-9);
  EXPECT_LT(p.model.rm.angularDistance(st.active.rm), 1e-9);
  EXPECT_EQ(again.persisted().cal_id, 3u);
  // What the records carried survives a restart (before: aligned and the configured noise).
  EXPECT_FALSE(p.output.aligned);
  EXPECT_EQ(p.output.sigma_f_nT, 0.75);
  EXPECT_EQ(p.output.sigma_enu_nT, 12.5);
}

TEST_F(CalibrationStoreTest, CorruptFileIsRefusedAndLeftUntouched) {
  const std::string text = "{\"schema\": \"magvec-calibration/1\", \"W\": [[1, 0";
  std::ofstream(dir_ / "cal.json", std::ios::binary) << text;
  CalibrationStore s(dir_.string());
  try {
    s.load();
    FAIL() << "a corrupt file was accepted";
  } catch (const DaemonError& e) {
    EXPECT_EQ(e.code(), kExitCorruptParams);
    EXPECT_NE(std::string(e.what()).find("cal.json"), std::string::npos);
  }
  EXPECT_EQ(read(dir_ / "cal.json"), text);
}

TEST_F(CalibrationStoreTest, FailedWriteIsReportedAndNotTakenAsPersisted) {
  CalibrationStore s(dir_.string());
  std::string error;
  ASSERT_TRUE(s.save(status(1), 0, "first", &error));
  // A state directory that does not exist: the atomic write cannot create its temporary file.
  CalibrationStore broken((dir_ / "missing" / "deeper").string());
  EXPECT_FALSE(broken.save(status(2), 0, "second", &error));
  EXPECT_NE(error.find("missing"), std::string::npos) << error;
  EXPECT_FALSE(broken.persisted().present);
  EXPECT_EQ(CalibrationStore(dir_.string()).load().cal_id, 1u);
}

}  // namespace
}  // namespace magvec::host::daemon
