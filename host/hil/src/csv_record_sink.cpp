// Record CSV sink; see csv_record_sink.hpp.
#include "magvec/host/hil/csv_record_sink.hpp"

#include <array>
#include <exception>

namespace magvec::host::hil {

const std::vector<std::string>& record_csv_columns() {
  static const std::vector<std::string> kColumns{
      "t_s",   "hx_nT", "hy_nT", "hz_nT", "hsx_nT", "hsy_nT",     "hsz_nT",      "F_nT",
      "hE_nT", "hN_nT", "hU_nT", "flags", "cal_id", "sigma_F_nT", "sigma_ENU_nT"};
  return kColumns;
}

CsvRecordSink::CsvRecordSink(const std::string& path, const std::vector<std::string>& comment_lines)
    : writer_(path, record_csv_columns(), comment_lines) {}

hal::Status CsvRecordSink::emit(const hal::OutputRecord& r) noexcept {
  const std::array<double, 15> row{static_cast<double>(r.t_us) * 1e-6,
                                   r.raw_nT[0],
                                   r.raw_nT[1],
                                   r.raw_nT[2],
                                   r.h_s_nT[0],
                                   r.h_s_nT[1],
                                   r.h_s_nT[2],
                                   r.f_nT,
                                   r.h_n_nT[0],
                                   r.h_n_nT[1],
                                   r.h_n_nT[2],
                                   static_cast<double>(r.flags),
                                   static_cast<double>(r.cal_id),
                                   r.sigma_f_nT,
                                   r.sigma_enu_nT};
  try {
    writer_.write_row(row);
  } catch (const std::exception& e) {
    last_error_ = e.what();
    return hal::Status::kBusError;
  }
  return hal::Status::kOk;
}

void CsvRecordSink::commit() {
  writer_.commit();
}

}  // namespace magvec::host::hil
