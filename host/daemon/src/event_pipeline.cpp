// EventPipeline; see event_pipeline.hpp.
#include "magvec/host/daemon/event_pipeline.hpp"

namespace magvec::host::daemon {

void EventPipeline::apply(const magvec_lcm::pipeline_event& e) {
  switch (e.kind) {
    case magvec_lcm::pipeline_event::SESSION_START: {
      Config c = parse_config(e.config_toml, "session configuration");
      auto p = Pipeline::create(c, sink_);
      // The old session's pending samples get their records before the new session starts.
      if (pipeline_) pipeline_->flush();
      pipeline_ = std::move(p);
      config_ = std::move(c);
      ++sessions_;
      return;
    }
    case magvec_lcm::pipeline_event::SET_ACTIVE:
      if (!pipeline_) {
        ++skipped_;
        return;
      }
      pipeline_->set_active(model_from_arrays(e.w, e.o_nT, e.rm_quat),
                            static_cast<std::uint32_t>(e.cal_id), output_quality_from(e));
      pipeline_->set_time_offset_s(e.time_offset_s);
      return;
    case magvec_lcm::pipeline_event::START_CALIBRATION:
      if (!pipeline_) {
        ++skipped_;
        return;
      }
      pipeline_->start_calibration();
      return;
    case magvec_lcm::pipeline_event::SOLVE_ON_WORKER:
      if (!pipeline_) {
        ++skipped_;
        return;
      }
      pipeline_->set_external_solve(true);
      return;
    case magvec_lcm::pipeline_event::REFERENCE:
      if (!pipeline_) {
        ++skipped_;
        return;
      }
      pipeline_->set_reference_sigma_nT(reference_sigma_from(e));
      return;
    case magvec_lcm::pipeline_event::SOLVE_RESULT:
      if (!pipeline_) {
        ++skipped_;
        return;
      }
      // A stale result (its calibration restarted first) is ignored, live and in a replay alike.
      if (!pipeline_->install_solve(solve_result_from(e))) ++stale_solves_;
      return;
    default:
      ++unknown_events_;
      return;
  }
}

void EventPipeline::flush() noexcept {
  if (pipeline_) pipeline_->flush();
}

void EventPipeline::apply(const magvec_lcm::mag_sample& m) noexcept {
  if (!pipeline_) {
    ++skipped_;
    return;
  }
  pipeline_->on_magnetometer(from_lcm(m), m.f_ref_nT);
}

void EventPipeline::apply(const magvec_lcm::mag_sample_batch& b) noexcept {
  if (b.count < 0 || static_cast<std::size_t>(b.count) != b.samples.size()) {
    ++malformed_batches_;
    return;
  }
  for (const magvec_lcm::mag_sample& m : b.samples)
    apply(m);
}

void EventPipeline::apply(const magvec_lcm::attitude& a) noexcept {
  if (!pipeline_) {
    ++skipped_;
    return;
  }
  pipeline_->on_attitude(from_lcm(a));
}

}  // namespace magvec::host::daemon
