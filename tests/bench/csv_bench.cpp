// Throughput of the CSV reader and writer (host/io/csv.hpp), per row of the simulation layout
// width.
#include <benchmark/benchmark.h>
#include <unistd.h>

#include <array>
#include <string>

#include "magvec/host/io/csv.hpp"

namespace {

const std::string& bench_file() {
  static const std::string path = [] {
    const std::string p = "/tmp/magvec_csv_bench_" + std::to_string(::getpid()) + ".csv";
    magvec::host::io::CsvWriter w(p, {"t_s", "hx_nT", "hy_nT", "hz_nT", "F_nT", "alpha_deg",
                                      "beta_deg", "gamma_deg", "theta_deg", "flags"});
    std::array<double, 10> row{};
    for (int i = 0; i < 200000; ++i) {
      row = {i * 0.005,
             12345.678901 + i,
             -23456.789012,
             34567.890123 - i,
             53729.1649758304,
             143.29873210417256,
             24.378347974554156,
             -81.04271333777615,
             0.0,
             0.0};
      w.write_row(row);
    }
    w.commit();
    return p;
  }();
  return path;
}

void BM_CsvReadRow(benchmark::State& state) {
  const std::string& p = bench_file();
  std::int64_t rows = 0;
  for (auto _ : state) {
    magvec::host::io::CsvReader r(p);
    magvec::host::io::CsvRecord rec;
    while (r.next(&rec))
      ++rows;
    benchmark::DoNotOptimize(rec);
  }
  state.SetItemsProcessed(rows);
}
BENCHMARK(BM_CsvReadRow)->Unit(benchmark::kMillisecond);

void BM_CsvWriteRow(benchmark::State& state) {
  const std::string p = bench_file() + ".out";
  std::int64_t rows = 0;
  for (auto _ : state) {
    magvec::host::io::CsvWriter w(p, {"t_s", "hx_nT", "hy_nT", "hz_nT", "F_nT"});
    std::array<double, 5> row{};
    for (int i = 0; i < 100000; ++i) {
      row = {i * 0.005, 12345.678901 + i, -23456.789012, 34567.890123 - i, 53729.1649758304};
      w.write_row(row);
    }
    w.commit();
    rows += 100000;
  }
  ::unlink(p.c_str());
  ::unlink(bench_file().c_str());
  state.SetItemsProcessed(rows);
}
BENCHMARK(BM_CsvWriteRow)->Unit(benchmark::kMillisecond);

}  // namespace
