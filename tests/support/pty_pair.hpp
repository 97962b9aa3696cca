// A pseudo-terminal pair for tests of serial devices: the test writes the instrument's bytes into
// the master end, the code under test opens the slave end by path (a symlink in a private
// directory, as /dev/serial/by-id/... would be). Non-blocking master writes are retried.
#pragma once

#include <fcntl.h>
#include <pty.h>
#include <unistd.h>

#include <array>
#include <cerrno>
#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <span>
#include <string>

namespace magvec::test {

class PtyPair {
 public:
  explicit PtyPair(const std::filesystem::path& link) {
    std::array<char, 128> name{};
    if (::openpty(&master_, &slave_, name.data(), nullptr, nullptr) != 0) std::abort();
    const std::filesystem::path tmp = link.string() + ".new";
    std::filesystem::remove(tmp);
    std::filesystem::create_symlink(name.data(), tmp);
    std::filesystem::rename(tmp, link);
  }
  ~PtyPair() {
    if (master_ >= 0) ::close(master_);
    close_slave();
  }
  PtyPair(const PtyPair&) = delete;
  PtyPair& operator=(const PtyPair&) = delete;

  // The test's own slave handle keeps the pty open until the driver has opened it by path.
  void close_slave() {
    if (slave_ >= 0) ::close(slave_);
    slave_ = -1;
  }
  // true when every byte was written.
  bool write_all(std::span<const std::uint8_t> bytes) const {
    std::size_t done = 0;
    while (done < bytes.size()) {
      const ssize_t r = ::write(master_, bytes.data() + done, bytes.size() - done);
      if (r < 0 && errno == EINTR) continue;
      if (r <= 0) return false;
      done += static_cast<std::size_t>(r);
    }
    return true;
  }

 private:
  int master_{-1};
  int slave_{-1};
};

}  // namespace magvec::test
