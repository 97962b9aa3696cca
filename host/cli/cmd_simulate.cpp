// `magvec simulate`: runs a simulated scenario (drivers/sim) and writes the recording as CSV, with
// a
// '#' header that states scenario, seed and the truth parameters so a calibration can be checked.
#include <CLI/CLI.hpp>
#include <iostream>
#include <memory>
#include <string>
#include <vector>

#include "commands.hpp"
#include "sim_csv.hpp"

namespace magvec::host::cli {
namespace {

struct SimulateOptions {
  std::string scenario;
  std::uint64_t seed = 1;
  std::string out;
  std::uint32_t samples = 0;
  std::uint32_t hold = 1;
  double rate_hz = 0;
  double noise_nT = 0;
  double ins_noise_deg = 0;
  double f_noise_nT = 0;
  double ins_latency_s = 0;
  std::string fixture = "plane-normal";
  double spike_rate = 0;
  double spike_nT = 1000;
  double dropout_rate = 0;
  std::vector<double> drift_nT_per_c;
  double temp_rate = 0;
  std::vector<double> diurnal_nT;
  double diurnal_period_s = 86400;
  std::vector<double> step_nT;
  double step_time_s = 0;
  double turntable_step_deg = 10;
};

core::Vec3<double> vec3(const std::vector<double>& v) {
  return core::Vec3<double>(v.at(0), v.at(1), v.at(2));
}

void run(const SimulateOptions& o, const CLI::App& sub) {
  const auto given = [&](const char* name) { return sub.count(name) > 0; };
  if (given("--fixture") && o.scenario != "sine-xz") {
    throw CLI::ValidationError("--fixture", "applies only to --scenario sine-xz");
  }
  if (given("--turntable-step-deg") && o.scenario.rfind("sine-", 0) != 0) {
    throw CLI::ValidationError("--turntable-step-deg",
                               "applies only to the sine-xy/sine-xz scenarios");
  }
  const drivers::sim::Fixture fixture = o.fixture == "housing-y"
                                            ? drivers::sim::Fixture::kHousingY
                                            : drivers::sim::Fixture::kPlaneNormal;
  drivers::sim::ScenarioConfig c = scenario_by_name(o.scenario, fixture);
  if (given("--samples")) c.num_samples = o.samples;
  if (given("--hold")) c.samples_per_attitude = o.hold;
  if (given("--rate-hz")) c.rate_hz = o.rate_hz;
  if (given("--noise-nT")) c.mag_noise_nT = o.noise_nT;
  if (given("--ins-noise-deg")) c.ins_noise_deg = o.ins_noise_deg;
  if (given("--f-noise-nT")) c.f_noise_nT = o.f_noise_nT;
  if (given("--ins-latency-s")) c.ins_latency_s = o.ins_latency_s;
  if (given("--turntable-step-deg")) c.turntable_step_deg = o.turntable_step_deg;
  c.spike_probability = o.spike_rate;
  c.spike_amplitude_nT = o.spike_nT;
  c.dropout_probability = o.dropout_rate;
  if (given("--drift-nT-per-C")) c.offset_drift_nT_per_c = vec3(o.drift_nT_per_c);
  c.temp_rate_c_per_s = o.temp_rate;
  if (given("--diurnal-nT")) c.diurnal_nT = vec3(o.diurnal_nT);
  c.diurnal_period_s = o.diurnal_period_s;
  if (given("--step-nT")) {
    c.step_nT = vec3(o.step_nT);
    if (!given("--step-time-s")) throw CLI::ValidationError("--step-nT", "needs --step-time-s");
    c.step_time_s = o.step_time_s;
  }
  if (c.ins_latency_s > 0 && !c.ins) {
    throw CLI::ValidationError("--ins-latency-s",
                               std::string("scenario ") + c.name + " has no INS");
  }
  drivers::sim::Simulator sim(c, o.seed);
  const std::uint64_t rows = write_sim_csv(&sim, o.out);
  std::cout << "magvec simulate: " << c.name << ", seed " << o.seed << ": " << rows << " rows -> "
            << o.out << "\n";
}

}  // namespace

void register_simulate(CLI::App& app) {
  auto opt = std::make_shared<SimulateOptions>();
  CLI::App* sub = app.add_subcommand(
      "simulate", "Simulate a scenario and write it as CSV (truth in the header)");
  sub->add_option("--scenario", opt->scenario, "Scenario")
      ->required()
      ->check(CLI::IsMember(scenario_names()));
  sub->add_option("--seed", opt->seed, "Random seed (the output is a deterministic function of it)")
      ->capture_default_str();
  sub->add_option("--out", opt->out, "Output CSV file (written atomically)")->required();
  sub->add_option("--samples", opt->samples,
                  "Number of magnetometer samples (default: the scenario's)")
      ->check(CLI::Range(1U, 100000000U));
  sub->add_option("--hold", opt->hold, "Samples per random attitude / turntable step")
      ->check(CLI::Range(1U, 1000000U));
  sub->add_option("--rate-hz", opt->rate_hz, "Magnetometer sample rate")
      ->check(CLI::Range(1e-6, 1e6));
  sub->add_option("--noise-nT", opt->noise_nT, "Magnetometer noise SD per axis")
      ->check(CLI::Range(0.0, 1e6));
  sub->add_option("--ins-noise-deg", opt->ins_noise_deg, "INS noise SD per Euler angle")
      ->check(CLI::Range(0.0, 90.0));
  sub->add_option("--f-noise-nT", opt->f_noise_nT, "Scalar reference noise SD")
      ->check(CLI::Range(0.0, 1e6));
  sub->add_option("--ins-latency-s", opt->ins_latency_s,
                  "INS latency (attitude refers to t - latency)")
      ->check(CLI::Range(0.0, 10.0));
  sub->add_option("--fixture", opt->fixture, "XZ-sweep fixture (sine-xz only)")
      ->check(CLI::IsMember({"plane-normal", "housing-y"}))
      ->capture_default_str();
  sub->add_option("--turntable-step-deg", opt->turntable_step_deg,
                  "Turntable step (negative: other direction)")
      ->check(CLI::Range(-180.0, 180.0));
  sub->add_option("--spike-rate", opt->spike_rate, "Spike probability per sample")
      ->check(CLI::Range(0.0, 1.0));
  sub->add_option("--spike-nT", opt->spike_nT, "Spike amplitude")
      ->check(CLI::Range(0.0, 1e7))
      ->capture_default_str();
  sub->add_option("--dropout-rate", opt->dropout_rate, "Dropout probability per sample")
      ->check(CLI::Range(0.0, 1.0));
  sub->add_option("--drift-nT-per-C", opt->drift_nT_per_c, "Offset drift with temperature x,y,z")
      ->expected(3)
      ->delimiter(',');
  sub->add_option("--temp-rate-C-per-s", opt->temp_rate, "Temperature ramp (from 20 C)")
      ->check(CLI::Range(-10.0, 10.0));
  sub->add_option("--diurnal-nT", opt->diurnal_nT, "Diurnal field variation amplitude E,N,U")
      ->expected(3)
      ->delimiter(',');
  sub->add_option("--diurnal-period-s", opt->diurnal_period_s, "Diurnal period")
      ->check(CLI::Range(1e-3, 1e9));
  sub->add_option("--step-nT", opt->step_nT, "Field step E,N,U (with --step-time-s)")
      ->expected(3)
      ->delimiter(',');
  sub->add_option("--step-time-s", opt->step_time_s, "Time of the field step");
  sub->callback([opt, sub] { run(*opt, *sub); });
}

}  // namespace magvec::host::cli
