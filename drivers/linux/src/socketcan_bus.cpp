// Linux transports: SocketCAN raw socket (Documentation/networking/can.rst: CAN_RAW_FILTER,
// CAN_RAW_ERR_FILTER, SO_TIMESTAMPNS, SO_RXQ_OVFL).
#include "magvec/drivers/linux/socketcan_bus.hpp"

#include <linux/can.h>
#include <linux/can/error.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstring>

#include "magvec/drivers/linux/linux_clock.hpp"

namespace magvec::drivers {
namespace {

constexpr std::uint32_t kStdIdMask = 0x7FFu;
constexpr std::uint32_t kExtIdMask = 0x1FFFFFFFu;

std::string hex(std::uint32_t v) {
  char buf[16];
  std::snprintf(buf, sizeof buf, "0x%X", v);
  return buf;
}

}  // namespace

std::unique_ptr<SocketCanBus> SocketCanBus::open(const SocketCanConfig& config, OsError* err) {
  const std::string name = "socketcan " + config.interface;
  if (config.interface.empty() || config.interface.size() >= IFNAMSIZ) {
    report_error(
        err, make_error(name, "configure", "interface name must have 1..15 characters", EINVAL));
    return nullptr;
  }
  std::vector<can_filter> filters;
  filters.reserve(config.filters.size());
  for (const CanFilterSpec& f : config.filters) {
    const std::uint32_t limit = f.extended ? kExtIdMask : kStdIdMask;
    if (f.id > limit || f.mask > limit) {
      report_error(
          err, make_error(name, "configure",
                          "filter id " + hex(f.id) + " / mask " + hex(f.mask) + " exceeds the " +
                              (f.extended ? "29" : "11") + "-bit identifier range",
                          EINVAL));
      return nullptr;
    }
    can_filter cf{};
    // CAN_EFF_FLAG in the mask makes the filter match only frames of the same format; RTR frames
    // are accepted as the data frames of the same ID.
    cf.can_id = f.id | (f.extended ? CAN_EFF_FLAG : 0u);
    cf.can_mask = f.mask | CAN_EFF_FLAG;
    filters.push_back(cf);
  }

  const int fd = ::socket(PF_CAN, SOCK_RAW | SOCK_CLOEXEC | SOCK_NONBLOCK, CAN_RAW);
  if (fd < 0) {
    const int e = errno;
    report_error(err,
                 make_os_error(name,
                               e == EAFNOSUPPORT ? "socket(AF_CAN) (kernel without CAN support?)"
                                                 : "socket(AF_CAN)",
                               e));
    return nullptr;
  }
  auto fail = [&](const char* op, int e) {
    ::close(fd);
    report_error(err, make_os_error(name, op, e));
    return nullptr;
  };
  const unsigned index = ::if_nametoindex(config.interface.c_str());
  if (index == 0) return fail("if_nametoindex (no such interface?)", errno);

  if (!config.filters.empty()) {
    if (::setsockopt(fd, SOL_CAN_RAW, CAN_RAW_FILTER, filters.data(),
                     static_cast<socklen_t>(filters.size() * sizeof(can_filter))) < 0) {
      return fail("setsockopt CAN_RAW_FILTER", errno);
    }
  }
  const can_err_mask_t err_mask = config.receive_error_frames ? CAN_ERR_MASK : 0u;
  if (::setsockopt(fd, SOL_CAN_RAW, CAN_RAW_ERR_FILTER, &err_mask, sizeof err_mask) < 0) {
    return fail("setsockopt CAN_RAW_ERR_FILTER", errno);
  }
  const int on = 1;
  if (::setsockopt(fd, SOL_SOCKET, SO_TIMESTAMPNS, &on, sizeof on) < 0) {
    return fail("setsockopt SO_TIMESTAMPNS", errno);
  }
  if (::setsockopt(fd, SOL_SOCKET, SO_RXQ_OVFL, &on, sizeof on) < 0) {
    return fail("setsockopt SO_RXQ_OVFL", errno);
  }
  sockaddr_can addr{};
  addr.can_family = AF_CAN;
  addr.can_ifindex = static_cast<int>(index);
  if (::bind(fd, reinterpret_cast<const sockaddr*>(&addr), sizeof addr) < 0) {
    return fail("bind", errno);
  }
  return std::unique_ptr<SocketCanBus>(new SocketCanBus(fd, config));
}

SocketCanBus::SocketCanBus(int fd, SocketCanConfig config)
    : fd_(fd), config_(std::move(config)), name_("socketcan " + config_.interface) {}

SocketCanBus::~SocketCanBus() {
  if (fd_ >= 0) ::close(fd_);
}

hal::Status SocketCanBus::receive(hal::CanFrame& out, std::uint32_t timeout_us) noexcept {
  const std::uint64_t deadline = monotonic_us() + timeout_us;
  for (;;) {
    can_frame frame{};
    iovec iov{&frame, sizeof frame};
    alignas(cmsghdr) char control[CMSG_SPACE(sizeof(timespec)) + CMSG_SPACE(sizeof(std::uint32_t))];
    msghdr msg{};
    msg.msg_iov = &iov;
    msg.msg_iovlen = 1;
    msg.msg_control = control;
    msg.msg_controllen = sizeof control;
    const ssize_t n = ::recvmsg(fd_, &msg, MSG_DONTWAIT);
    if (n < 0) {
      const int e = errno;
      if (e == EINTR) continue;
      if (e != EAGAIN && e != EWOULDBLOCK) {
        assign_os_error(last_error_, name_, "recvmsg", e);
        return hal::Status::kBusError;
      }
      const std::uint64_t now = monotonic_us();
      if (now >= deadline) return hal::Status::kTimeout;
      pollfd pfd{fd_, POLLIN, 0};
      const timespec ts = timespec_from_us(deadline - now);
      const int rc = ::ppoll(&pfd, 1, &ts, nullptr);
      if (rc < 0 && errno != EINTR) {
        assign_os_error(last_error_, name_, "poll", errno);
        return hal::Status::kBusError;
      }
      if (rc == 0) return hal::Status::kTimeout;
      if (rc > 0 && (pfd.revents & (POLLERR | POLLNVAL)) != 0 && (pfd.revents & POLLIN) == 0) {
        assign_error(last_error_, name_, "poll", "socket error (interface down?)", ENETDOWN);
        return hal::Status::kBusError;
      }
      continue;
    }
    const std::uint64_t t_call = monotonic_us();
    if (static_cast<std::size_t>(n) != sizeof(can_frame)) {
      assign_error(last_error_, name_, "recvmsg", "short frame", EPROTO);
      return hal::Status::kBusError;
    }
    std::uint64_t t_us = 0;
    for (cmsghdr* c = CMSG_FIRSTHDR(&msg); c != nullptr; c = CMSG_NXTHDR(&msg, c)) {
      if (c->cmsg_level != SOL_SOCKET) continue;
      if (c->cmsg_type == SO_TIMESTAMPNS) {
        timespec ts{};
        std::memcpy(&ts, CMSG_DATA(c), sizeof ts);
        t_us = realtime_to_monotonic_us(ts);
      } else if (c->cmsg_type == SO_RXQ_OVFL) {
        std::uint32_t dropped = 0;
        std::memcpy(&dropped, CMSG_DATA(c), sizeof dropped);
        dropped_frames_ = dropped;  // the kernel's cumulative count for this socket
      }
    }
    // A timestamp after the call (clock offset jitter) or missing falls back to the call time.
    if (t_us == 0 || t_us > t_call) t_us = t_call;

    out = hal::CanFrame{};
    out.t_us = t_us;
    out.extended = (frame.can_id & CAN_EFF_FLAG) != 0;
    out.id = frame.can_id & (out.extended ? CAN_EFF_MASK : CAN_SFF_MASK);
    out.dlc = frame.len > 8 ? std::uint8_t{8} : frame.len;
    if ((frame.can_id & CAN_RTR_FLAG) == 0) std::memcpy(out.data.data(), frame.data, out.dlc);
    if ((frame.can_id & CAN_ERR_FLAG) != 0) {
      ++error_frames_;
      last_error_class_ = frame.can_id & CAN_ERR_MASK;
      out.id = last_error_class_;
      assign_error(last_error_, name_, "receive",
                   "CAN error frame (class bits in last_error_class)", EIO);
      return hal::Status::kBusError;
    }
    return hal::Status::kOk;
  }
}

hal::Status SocketCanBus::send(const hal::CanFrame& f) noexcept {
  if (f.dlc > 8 || f.id > (f.extended ? kExtIdMask : kStdIdMask)) {
    return hal::Status::kInvalidArgument;
  }
  can_frame frame{};
  frame.can_id = f.id | (f.extended ? CAN_EFF_FLAG : 0u);
  frame.len = f.dlc;
  std::memcpy(frame.data, f.data.data(), f.dlc);
  for (;;) {
    const ssize_t n = ::send(fd_, &frame, sizeof frame, MSG_DONTWAIT);
    if (n == static_cast<ssize_t>(sizeof frame)) return hal::Status::kOk;
    const int e = n < 0 ? errno : EIO;
    if (e == EINTR) continue;
    assign_os_error(last_error_, name_, "send", e);
    return e == EAGAIN || e == EWOULDBLOCK || e == ENOBUFS ? hal::Status::kOverflow
                                                           : hal::Status::kBusError;
  }
}

}  // namespace magvec::drivers
