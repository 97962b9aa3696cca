// hal::RecordSink writing the `magvec run` / `magvec apply` record CSV
// (docs/conventions.md#file-formats):
//   t_s,hx_nT,hy_nT,hz_nT,hsx_nT,hsy_nT,hsz_nT,F_nT,hE_nT,hN_nT,hU_nT,flags,cal_id,sigma_F_nT,sigma_ENU_nT
// hx..hz are the raw reading; hs* the compensated orthogonal sensor frame; hE/hN/hU the ENU
// components (nan without attitude); nan marks values that do not exist for a record.
// Host only: the file is written atomically by host::io::CsvWriter on commit().
#pragma once

#include <string>
#include <vector>

#include "magvec/hal/record_sink.hpp"
#include "magvec/host/io/csv.hpp"

namespace magvec::host::hil {

const std::vector<std::string>& record_csv_columns();

class CsvRecordSink final : public hal::RecordSink {
 public:
  CsvRecordSink(const std::string& path, const std::vector<std::string>& comment_lines = {});
  // kBusError if the row could not be written (the error text is kept in last_error()).
  hal::Status emit(const hal::OutputRecord& record) noexcept override;
  void commit();
  std::uint64_t rows() const noexcept { return writer_.rows(); }
  const std::string& last_error() const noexcept { return last_error_; }

 private:
  io::CsvWriter writer_;
  std::string last_error_;
};

}  // namespace magvec::host::hil
