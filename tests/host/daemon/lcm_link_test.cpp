// magvecd's LCM links (host/daemon lcm_link.hpp) and the command URL derivation (config.hpp).
#include "magvec/host/daemon/lcm_link.hpp"

#include <gtest/gtest.h>

#include <vector>

#include "magvec/host/daemon/config.hpp"
#include "magvec/host/daemon/daemon_error.hpp"

namespace magvec::host::daemon {
namespace {

TEST(CommandUrl, UdpmMovesToTheNextPortOtherProvidersStay) {
  EXPECT_EQ(command_url_for("udpm://239.255.76.67:7667?ttl=0"), "udpm://239.255.76.67:7668?ttl=0");
  EXPECT_EQ(command_url_for("udpm://239.1.2.3:9000"), "udpm://239.1.2.3:9001");
  EXPECT_EQ(command_url_for("udpm://"), "udpm://239.255.76.67:7668");
  EXPECT_EQ(command_url_for("udpm://?ttl=1"), "udpm://239.255.76.67:7668?ttl=1");
  EXPECT_EQ(command_url_for("memq://"), "memq://");
  EXPECT_EQ(command_url_for("udpm://239.1.2.3:notaport"), "udpm://239.1.2.3:notaport");
  LcmConfig c;
  EXPECT_EQ(command_url(c), "udpm://239.255.76.67:7668?ttl=0");
  c.command_url = "udpm://239.9.9.9:1234?ttl=0";
  EXPECT_EQ(command_url(c), "udpm://239.9.9.9:1234?ttl=0");
}

TEST(CommandUrl, AnExplicitCommandUrlMustDifferFromTheDataUrl) {
  EXPECT_THROW(parse_config("[lcm]\nurl = \"udpm://239.1.1.1:7000\"\n"
                            "command_url = \"udpm://239.1.1.1:7000\"\n",
                            "test"),
               ConfigError);
  EXPECT_NO_THROW(parse_config("[lcm]\ncommand_url = \"udpm://239.1.1.1:7001\"\n", "test"));
}

TEST(CommandLink, HandlesACommandThatArrived) {
  std::vector<std::string> got;
  CommandLink link("memq://", "CMD",
                   [&](const magvec_lcm::command& c) { got.push_back(c.command); });
  link.wait(0);
  EXPECT_TRUE(got.empty());
  magvec_lcm::command c{};
  c.request_id = 1;
  c.command = "status";
  ASSERT_EQ(link.lcm().publish("CMD", &c), 0);
  link.wait(100'000);
  ASSERT_EQ(got.size(), 1u);
  EXPECT_EQ(got[0], "status");
}

TEST(LcmLinks, AnUnknownProviderIsTheLcmExitCode) {
  try {
    LcmPublisher p("nosuchprovider://x", "OUT");
    FAIL();
  } catch (const DaemonError& e) {
    EXPECT_EQ(e.code(), kExitLcm);
    EXPECT_NE(std::string(e.what()).find("nosuchprovider://x"), std::string::npos);
  }
}

}  // namespace
}  // namespace magvec::host::daemon
