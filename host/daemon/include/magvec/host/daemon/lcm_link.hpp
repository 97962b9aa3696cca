// magvecd's two LCM instances.
//   LcmPublisher: the data URL, publish only. It never subscribes (LCM's udpm provider creates its
//     receive socket and thread on the first subscribe or handle), so the daemon does not receive
//     its own messages back: on udpm every receiver of a group:port gets every message sent there,
//     whatever the channel, and at 1 kHz that receive path cost several times the pipeline.
//   CommandLink: the command URL (lcm.command_url, by default another udpm port), where `magvec
//     ctl` sends commands and receives the replies; low traffic, so waiting on it is cheap.
#pragma once

#include <cstdint>
#include <functional>
#include <lcm/lcm-cpp.hpp>
#include <memory>
#include <string>

#include "magvec/hal/record_sink.hpp"
#include "magvec/host/daemon/lcm_codec.hpp"

namespace magvec::host::daemon {

class LcmPublisher final : public hal::RecordSink {
 public:
  // Throws DaemonError(kExitLcm) when the provider is not available.
  LcmPublisher(const std::string& url, std::string output_channel);

  template <typename Msg>
  void publish(const std::string& channel, const Msg& m) noexcept {
    if (lcm_->publish(channel, &m) != 0) ++errors_;
  }
  // The records of the pipeline, on the output channel.
  hal::Status emit(const hal::OutputRecord& r) noexcept override;
  std::uint64_t errors() const noexcept { return errors_; }

 private:
  std::unique_ptr<lcm::LCM> lcm_;
  std::string output_channel_;
  std::uint64_t errors_{0};
};

class CommandLink {
 public:
  using Handler = std::function<void(const magvec_lcm::command&)>;
  // Throws DaemonError(kExitLcm) when the provider is not available.
  CommandLink(const std::string& url, const std::string& command_channel, Handler handler);

  // Waits up to `us` microseconds (0: only looks) for a command and handles those that came.
  void wait(std::uint32_t us);
  void reply(const std::string& channel, const magvec_lcm::command_reply& r) noexcept;
  // The instance (tests publish commands through it).
  lcm::LCM& lcm() noexcept { return *lcm_; }

 private:
  void on_command(const lcm::ReceiveBuffer*, const std::string&, const magvec_lcm::command* c);

  std::unique_ptr<lcm::LCM> lcm_;
  Handler handler_;
  int fd_{-1};
};

}  // namespace magvec::host::daemon
