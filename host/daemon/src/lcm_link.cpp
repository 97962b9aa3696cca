// magvecd's LCM instances; see lcm_link.hpp.
#include "magvec/host/daemon/lcm_link.hpp"

#include <poll.h>

#include <cerrno>
#include <ctime>
#include <utility>

#include "magvec/host/daemon/daemon_error.hpp"

namespace magvec::host::daemon {
namespace {

std::unique_ptr<lcm::LCM> open_lcm(const std::string& url) {
  auto l = std::make_unique<lcm::LCM>(url);
  if (!l->good()) throw DaemonError(kExitLcm, "LCM provider " + url + " is not available");
  return l;
}

}  // namespace

LcmPublisher::LcmPublisher(const std::string& url, std::string output_channel)
    : lcm_(open_lcm(url)), output_channel_(std::move(output_channel)) {}

hal::Status LcmPublisher::emit(const hal::OutputRecord& r) noexcept {
  const magvec_lcm::calibrated_vector v = to_lcm(r);
  if (lcm_->publish(output_channel_, &v) != 0) {
    ++errors_;
    return hal::Status::kBusError;
  }
  return hal::Status::kOk;
}

CommandLink::CommandLink(const std::string& url, const std::string& command_channel,
                         Handler handler)
    : lcm_(open_lcm(url)), handler_(std::move(handler)) {
  lcm_->subscribe(command_channel, &CommandLink::on_command, this);
  fd_ = lcm_->getFileno();
}

void CommandLink::wait(std::uint32_t us) {
  // ppoll: microsecond waits (handleTimeout rounds up to whole milliseconds, which at 1 kHz
  // oversleeps a whole period).
  pollfd p{fd_, POLLIN, 0};
  timespec ts{static_cast<time_t>(us / 1'000'000), static_cast<long>(us % 1'000'000) * 1000};
  if (::ppoll(&p, 1, &ts, nullptr) > 0 && (p.revents & POLLIN) != 0) lcm_->handle();
}

void CommandLink::reply(const std::string& channel, const magvec_lcm::command_reply& r) noexcept {
  (void)lcm_->publish(channel, &r);
}

void CommandLink::on_command(const lcm::ReceiveBuffer*, const std::string&,
                             const magvec_lcm::command* c) {
  handler_(*c);
}

}  // namespace magvec::host::daemon
