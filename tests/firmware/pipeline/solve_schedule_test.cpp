// SolveSchedule (firmware/pipeline/.../solve_schedule.hpp): a ticket is seen once, its result is
// due exactly install_after_records records after the record that raised it, and a new ticket
// (a restarted calibration) replaces a pending one.
#include "magvec/pipeline/solve_schedule.hpp"

#include <gtest/gtest.h>

#include <cstdint>

namespace magvec {
namespace {

// What SolveSchedule reads of a SensorLoop.
struct FakeLoop {
  core::CalState s{core::CalState::kCollecting};
  std::uint32_t ticket{0};
  core::CalState state() const noexcept { return s; }
  std::uint32_t solve_ticket() const noexcept { return ticket; }
};

TEST(SolveSchedule, DueAFixedNumberOfRecordsAfterTheTicket) {
  pipeline::SolveSchedule sched(8);
  FakeLoop loop;
  EXPECT_FALSE(sched.raised(loop, 1));
  EXPECT_FALSE(sched.due(1));
  loop.s = core::CalState::kSolving;
  loop.ticket = 1;
  EXPECT_TRUE(sched.raised(loop, 10));
  EXPECT_FALSE(sched.raised(loop, 11));  // the same ticket is raised once
  EXPECT_TRUE(sched.pending());
  EXPECT_EQ(sched.ticket(), 1u);
  EXPECT_EQ(sched.ticket_record(), 10u);
  for (std::uint32_t r = 10; r < 18; ++r)
    EXPECT_FALSE(sched.due(r)) << r;
  EXPECT_TRUE(sched.due(18));
  sched.installed();
  EXPECT_FALSE(sched.pending());
  EXPECT_FALSE(sched.due(19));
  // Installed: the loop validates; the old ticket is not raised again.
  loop.s = core::CalState::kValidating;
  EXPECT_FALSE(sched.raised(loop, 19));
}

TEST(SolveSchedule, NewTicketReplacesAPendingOne) {
  pipeline::SolveSchedule sched(8);
  FakeLoop loop{core::CalState::kSolving, 1};
  EXPECT_TRUE(sched.raised(loop, 5));
  loop.ticket = 2;  // the calibration restarted and became ready again
  EXPECT_TRUE(sched.raised(loop, 9));
  EXPECT_EQ(sched.ticket(), 2u);
  EXPECT_FALSE(sched.due(16));
  EXPECT_TRUE(sched.due(17));
}

TEST(SolveSchedule, ZeroRecordsIsDueOnTheTicketsRecord) {
  pipeline::SolveSchedule sched(0);
  FakeLoop loop{core::CalState::kSolving, 3};
  EXPECT_TRUE(sched.raised(loop, 42));
  EXPECT_TRUE(sched.due(42));
}

}  // namespace
}  // namespace magvec
