// CalibrationStore (host/daemon persistence.hpp): magvecd's cal.json round trip, a missing file,
// a corrupt or truncated file refused and left byte for byte, a failed write keeping the previous
// file; and the persistence rows of the fault matrix: a writer killed (SIGKILL) at every system
// call of a persist, a full disk and a read-only state directory (a private tmpfs in a user and
// mount namespace). After every fault the last good cal.json is byte-identical or the new one is
// complete, and the store loads it. With MAGVEC_PERSIST_FAULT_TABLE=FILE the rows of the README's
// table are appended to FILE.
#include "magvec/host/daemon/persistence.hpp"

#include <fcntl.h>
#include <gtest/gtest.h>
#include <sched.h>
#include <sys/mount.h>
#include <sys/ptrace.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <csignal>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>

#include "magvec/host/daemon/daemon_error.hpp"

namespace magvec::host::daemon {
namespace {

std::string file_text(const std::filesystem::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::ostringstream os;
  os << in.rdbuf();
  return os.str();
}

CalibrationStatus status(std::uint32_t cal_id) {
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

class CalibrationStoreTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = std::filesystem::temp_directory_path() /
           ("magvec_store_test_" + std::to_string(::getpid()));
    std::filesystem::remove_all(dir_);
    std::filesystem::create_directories(dir_);
  }
  void TearDown() override { std::filesystem::remove_all(dir_); }
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
  EXPECT_EQ(file_text(dir_ / "cal.json"), text);
}

TEST_F(CalibrationStoreTest, TruncatedFileIsRefusedAndLeftUntouched) {
  CalibrationStore s(dir_.string());
  std::string error;
  ASSERT_TRUE(s.save(status(4), 0, "test", &error)) << error;
  const std::string whole = file_text(dir_ / "cal.json");
  for (const std::size_t keep : {std::size_t{0}, whole.size() / 2, whole.size() - 2}) {
    const std::string cut = whole.substr(0, keep);
    std::ofstream(dir_ / "cal.json", std::ios::binary | std::ios::trunc) << cut;
    EXPECT_THROW(CalibrationStore(dir_.string()).load(), DaemonError) << keep << " bytes";
    EXPECT_EQ(file_text(dir_ / "cal.json"), cut) << keep << " bytes";
  }
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

// --- Persistence faults (the README's fault matrix, persistence rows) -------------------------

void table_row(const std::string& row) {
  std::printf("%s\n", row.c_str());
  if (const char* path = std::getenv("MAGVEC_PERSIST_FAULT_TABLE"); path != nullptr) {
    std::ofstream f(path, std::ios::app);
    f << row << '\n';
  }
}

std::vector<std::string> leftover_names(const std::filesystem::path& dir) {
  std::vector<std::string> names;
  for (const auto& e : std::filesystem::directory_iterator(dir)) {
    const std::string n = e.path().filename().string();
    if (n != "cal.json") names.push_back(n);
  }
  return names;
}

// Runs save(st) in a child traced with PTRACE_SYSCALL and kills it (SIGKILL) at its
// `kill_at`-th system-call stop (entry and exit stops both count: killed before a call runs and
// after it returned). Returns the number of stops seen when the child finished without being
// killed (kill_at beyond its last stop), 0 when it was killed, -1 when tracing is not possible.
int persist_killed_at(const std::filesystem::path& dir, const CalibrationStatus& st, int kill_at,
                      std::string* why) {
  const pid_t pid = ::fork();
  if (pid < 0) {
    *why = std::string("fork: ") + std::strerror(errno);
    return -1;
  }
  if (pid == 0) {
    if (::ptrace(PTRACE_TRACEME, 0, nullptr, nullptr) != 0) ::_exit(90);
    ::raise(SIGSTOP);
    CalibrationStore s(dir.string());
    std::string error;
    ::_exit(s.save(st, 0, "killed-writer test", &error) ? 0 : 91);
  }
  int wst = 0;
  if (::waitpid(pid, &wst, 0) != pid || !WIFSTOPPED(wst)) {
    *why = WIFEXITED(wst) && WEXITSTATUS(wst) == 90 ? "PTRACE_TRACEME refused"
                                                    : "the child did not stop";
    return -1;
  }
  ::ptrace(PTRACE_SETOPTIONS, pid, nullptr,
           reinterpret_cast<void*>(PTRACE_O_TRACESYSGOOD | PTRACE_O_EXITKILL));
  int stops = 0;
  int pass_signal = 0;
  while (true) {
    if (::ptrace(PTRACE_SYSCALL, pid, nullptr,
                 reinterpret_cast<void*>(std::intptr_t{pass_signal})) != 0) {
      *why = std::string("PTRACE_SYSCALL: ") + std::strerror(errno);
      ::kill(pid, SIGKILL);
      ::waitpid(pid, &wst, 0);
      return -1;
    }
    pass_signal = 0;
    if (::waitpid(pid, &wst, 0) != pid) return -1;
    if (WIFEXITED(wst)) {
      if (WEXITSTATUS(wst) != 0) {
        *why = "the uninterrupted save failed (exit " + std::to_string(WEXITSTATUS(wst)) + ")";
        return -1;
      }
      return stops;
    }
    if (WIFSIGNALED(wst)) {
      *why = "the child died of signal " + std::to_string(WTERMSIG(wst));
      return -1;
    }
    if (WSTOPSIG(wst) == (SIGTRAP | 0x80)) {
      if (++stops == kill_at) {
        ::kill(pid, SIGKILL);
        ::waitpid(pid, &wst, 0);
        return 0;
      }
    } else {
      pass_signal = WSTOPSIG(wst);  // a signal of its own: deliver it
    }
  }
}

TEST_F(CalibrationStoreTest, AWriterKilledAtEverySystemCallLeavesTheLastGoodOrTheNewFile) {
  const CalibrationStatus st = status(2);
  int kills = 0, kept_old = 0, complete_new = 0, leftovers = 0;
  for (int k = 1; k < 10000; ++k) {
    // The last good file, written fresh before each kill.
    std::filesystem::remove_all(dir_);
    std::filesystem::create_directories(dir_);
    std::string error;
    ASSERT_TRUE(CalibrationStore(dir_.string()).save(status(1), 0, "last good", &error)) << error;
    const std::string last_good = file_text(dir_ / "cal.json");

    std::string why;
    const int finished = persist_killed_at(dir_, st, k, &why);
    if (finished < 0) GTEST_SKIP() << "cannot trace a child here: " << why;
    CalibrationStore after(dir_.string());
    const PersistedCalibration p = after.load();  // never throws: nothing half-written
    ASSERT_TRUE(p.present) << "killed at stop " << k;
    EXPECT_TRUE(leftover_names(dir_).empty()) << "killed at stop " << k;
    leftovers += static_cast<int>(after.leftovers_removed());
    if (finished > 0) {
      // Not killed: the writer ran to its end before stop k.
      EXPECT_LT(finished, k);
      EXPECT_EQ(p.cal_id, 2u);
      break;
    }
    ++kills;
    if (file_text(dir_ / "cal.json") == last_good) {
      ++kept_old;
      EXPECT_EQ(p.cal_id, 1u);
    } else {
      ++complete_new;  // killed after its rename(): the new file, whole
      EXPECT_EQ(p.cal_id, 2u) << "killed at stop " << k;
      EXPECT_LT((p.model.w - st.active.w).norm(), 1e-12);
    }
  }
  // The run must have hit both sides of the rename, and killed writes must have left temporary
  // files for load() to remove (else this test proves nothing about an interrupted write).
  EXPECT_GT(kept_old, 0);
  EXPECT_GT(complete_new, 0);
  EXPECT_GT(leftovers, 0);
  table_row("| writer killed (SIGKILL) at every system-call stop of one persist | " +
            std::to_string(kills) + " kills, one per stop | the daemon's load at the next start: " +
            std::to_string(leftovers) + " temporary files of killed writes removed | " +
            std::to_string(kept_old) + " times the last good cal.json byte-identical (killed " +
            "before rename), " + std::to_string(complete_new) +
            " times the new one complete (after); never a partial file | the next start loads " +
            "it |");
}

// Runs `body` in a child that is root of its own user and mount namespaces with a private tmpfs
// of `size` mounted on `dir`; returns its report (key=value lines), or nothing (and why) when the
// namespaces are not available.
std::map<std::string, std::string> in_private_tmpfs(const std::filesystem::path& dir,
                                                    const char* size,
                                                    void (*body)(const std::filesystem::path&, int),
                                                    std::string* why) {
  int fds[2];
  if (::pipe(fds) != 0) return {};
  const uid_t uid = ::getuid();
  const gid_t gid = ::getgid();
  const pid_t pid = ::fork();
  if (pid == 0) {
    ::close(fds[0]);
    auto say = [&](const std::string& line) {
      const std::string l = line + "\n";
      (void)!::write(fds[1], l.data(), l.size());
    };
    if (::unshare(CLONE_NEWUSER | CLONE_NEWNS) != 0) {
      say(std::string("unavailable=unshare: ") + std::strerror(errno));
      ::_exit(0);
    }
    auto put = [](const char* file, const std::string& text) {
      std::ofstream f(file);
      f << text;
      return f.good();
    };
    if (!put("/proc/self/setgroups", "deny") ||
        !put("/proc/self/uid_map", "0 " + std::to_string(uid) + " 1") ||
        !put("/proc/self/gid_map", "0 " + std::to_string(gid) + " 1")) {
      say("unavailable=cannot write the namespace's id maps");
      ::_exit(0);
    }
    if (::mount("none", "/", nullptr, MS_REC | MS_PRIVATE, nullptr) != 0 ||
        ::mount("magvec-test", dir.c_str(), "tmpfs", 0, size) != 0) {
      say(std::string("unavailable=mount tmpfs: ") + std::strerror(errno));
      ::_exit(0);
    }
    body(dir, fds[1]);
    ::_exit(0);
  }
  ::close(fds[1]);
  std::string text;
  char buf[512];
  ssize_t n;
  while ((n = ::read(fds[0], buf, sizeof buf)) > 0)
    text.append(buf, static_cast<std::size_t>(n));
  ::close(fds[0]);
  int wst = 0;
  ::waitpid(pid, &wst, 0);
  std::map<std::string, std::string> report;
  std::istringstream lines(text);
  for (std::string line; std::getline(lines, line);) {
    const auto eq = line.find('=');
    if (eq != std::string::npos) report[line.substr(0, eq)] = line.substr(eq + 1);
  }
  if (!WIFEXITED(wst) || WEXITSTATUS(wst) != 0) report["child_failed"] = std::to_string(wst);
  if (report.count("unavailable") != 0U) *why = report["unavailable"];
  return report;
}

void report_line(int fd, const std::string& key, const std::string& value) {
  const std::string l = key + "=" + value + "\n";
  (void)!::write(fd, l.data(), l.size());
}

// The child's side of a failed-save case: the last good file, `inject` (the fault), a save that
// must fail, the file and the store checked, `clear` (the fault gone), a save that must succeed.
// `own_files` are the files `inject` leaves in the directory besides cal.json.
using FaultStep = bool (*)(const std::filesystem::path& dir, int fd);
void failed_save_body(const std::filesystem::path& dir, int fd, FaultStep inject, FaultStep clear,
                      std::size_t own_files) {
  std::string error;
  if (!CalibrationStore(dir.string()).save(status(1), 0, "last good", &error)) {
    report_line(fd, "setup", error);
    return;
  }
  const std::string last_good = file_text(dir / "cal.json");
  if (!inject(dir, fd)) return;
  CalibrationStore s(dir.string());
  s.load();
  const bool saved = s.save(status(2), 0, "under the fault", &error);
  report_line(fd, "saved", saved ? "1" : "0");
  report_line(fd, "error", error);
  report_line(fd, "identical", file_text(dir / "cal.json") == last_good ? "1" : "0");
  report_line(fd, "persisted_id", std::to_string(s.persisted().cal_id));
  report_line(fd, "leftovers", std::to_string(leftover_names(dir).size() - own_files));
  report_line(fd, "reload_id", std::to_string(CalibrationStore(dir.string()).load().cal_id));
  if (!clear(dir, fd)) return;
  error.clear();
  report_line(fd, "recovered", s.save(status(2), 0, "fault gone", &error) ? "1" : error);
  report_line(fd, "recovered_id", std::to_string(CalibrationStore(dir.string()).load().cal_id));
}

bool fill_disk(const std::filesystem::path& dir, int fd) {
  const int filler = ::open((dir / "filler").c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0600);
  const std::string block(512, 'x');
  while (::write(filler, block.data(), block.size()) > 0) {
  }
  report_line(fd, "filler_errno", std::to_string(errno));
  ::close(filler);
  return true;
}
bool free_disk(const std::filesystem::path& dir, int /*fd*/) {
  return std::filesystem::remove(dir / "filler");
}
bool remount(const std::filesystem::path& dir, int fd, unsigned long flags, const char* key) {
  if (::mount(nullptr, dir.c_str(), nullptr, MS_REMOUNT | flags, nullptr) == 0) return true;
  report_line(fd, key, std::string("remount: ") + std::strerror(errno));
  return false;
}
bool read_only(const std::filesystem::path& dir, int fd) {
  return remount(dir, fd, MS_RDONLY, "setup");
}
bool writable(const std::filesystem::path& dir, int fd) {
  return remount(dir, fd, 0, "recovered");
}

void disk_full_body(const std::filesystem::path& dir, int fd) {
  failed_save_body(dir, fd, fill_disk, free_disk, 1);
}
void read_only_body(const std::filesystem::path& dir, int fd) {
  failed_save_body(dir, fd, read_only, writable, 0);
}

// The error text with the test's directory replaced (the README's table shows no temporary path).
std::string without_dir(std::string text, const std::filesystem::path& dir) {
  const std::string d = dir.string();
  for (auto at = text.find(d); at != std::string::npos; at = text.find(d))
    text.replace(at, d.size(), "<state_dir>");
  return text;
}

void expect_failed_write_kept_the_last_good(std::map<std::string, std::string>& r,
                                            const std::string& errno_text) {
  ASSERT_EQ(r.count("setup"), 0U) << r["setup"];
  EXPECT_EQ(r.count("child_failed"), 0U) << r["child_failed"];
  EXPECT_EQ(r["saved"], "0");
  EXPECT_NE(r["error"].find(errno_text), std::string::npos) << r["error"];
  EXPECT_EQ(r["identical"], "1");
  EXPECT_EQ(r["persisted_id"], "1");  // not taken as persisted
  EXPECT_EQ(r["leftovers"], "0");     // the failed write's temporary file removed
  EXPECT_EQ(r["reload_id"], "1");
  EXPECT_EQ(r["recovered"], "1");
  EXPECT_EQ(r["recovered_id"], "2");
}

TEST_F(CalibrationStoreTest, ADiskFullKeepsTheLastGoodFileAndTheNextSaveRecovers) {
  std::string why;
  auto r = in_private_tmpfs(dir_, "size=16k", disk_full_body, &why);
  if (!why.empty()) GTEST_SKIP() << "no private tmpfs here: " << why;
  EXPECT_EQ(r["filler_errno"], std::to_string(ENOSPC));
  expect_failed_write_kept_the_last_good(r, std::strerror(ENOSPC));
  table_row("| state directory full (ENOSPC; a 16-KiB tmpfs) | one save | save() false with \"" +
            without_dir(r["error"], dir_) + "\", not marked persisted | " +
            "last good cal.json byte-identical, no temporary file left | the next save after " +
            "space is freed writes the new one |");
}

TEST_F(CalibrationStoreTest, AReadOnlyStateDirectoryKeepsTheLastGoodFileAndTheNextSaveRecovers) {
  std::string why;
  auto r = in_private_tmpfs(dir_, "size=64k", read_only_body, &why);
  if (!why.empty()) GTEST_SKIP() << "no private tmpfs here: " << why;
  expect_failed_write_kept_the_last_good(r, std::strerror(EROFS));
  table_row("| state directory read-only (EROFS; the tmpfs remounted read-only) | one save | " +
            std::string("save() false with \"") + without_dir(r["error"], dir_) +
            "\", not marked persisted | last good cal.json byte-identical and loadable | the " +
            "next save after the remount read-write writes the new one |");
}

}  // namespace
}  // namespace magvec::host::daemon
