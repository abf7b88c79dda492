// The device side of mrctl's serial protocol (see mrctl_device.h, docs/protocol.md §5-§7).
#include "mrctl_device.h"

#include <math.h>

#include <limits>

namespace mrctl_fw {

namespace {
constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();  // 0x7FC00000
constexpr float kTwoPi = 6.28318530717958647692f;
}  // namespace

Device::Device(const DeviceConfig& cfg, DeviceIo& io) : cfg_(cfg), io_(io), rx_(*this) {
  if (cfg_.velocity_cutoff_hz > 0.0f && cfg_.sample_period_s > 0.0f)
    v_alpha_ = expf(-kTwoPi * cfg_.velocity_cutoff_hz * cfg_.sample_period_s);
  // no measurement yet: a reply before the first tick says so
  meas_.x_m = meas_.v_mps = meas_.F_N = kNaN;
  meas_status_ = kStatusSensorFault | (cfg_.has_load_cell ? 0 : kStatusNoLoadCell);
  // the I/O is not touched here (a global object is built before the board is
  // set up): the board holds 0 A and the driver disabled until the first tick
}

// --- receiving ------------------------------------------------------------------

void Device::receive(const uint8_t* data, size_t n, uint32_t now_us) {
  now_us_ = now_us;
  watchdog(now_us);
  rx_.push(data, n);
}

void Device::on_setpoint_crc_error() {
  // §2.3: echo the last good host seq; the applied current is not changed
  send_error(last_good_seq_, kErrBadCrc);
}

void Device::on_frame(const uint8_t* frame, size_t len) {
  const uint8_t version = frame[2];
  const uint8_t type = frame[3];
  const uint32_t seq = get_u32(frame + 5);
  if (version != kVersion) {  // §7: say which version we speak; apply nothing
    rx_error_ = true;
    send_error(seq, kErrBadVersion, kVersion);
    return;
  }
  if (type == kTypeSetpoint) {
    setpoint(decode_setpoint(frame));
  } else if (type == kTypeChannelQuery) {  // §2.5: no extra channels on this device
    uint8_t out[kHeaderSize + 4 + kCrcSize];
    const size_t m = encode_channel_list(out, sizeof out, meas_.seq, seq, "");
    if (m) io_.send(out, m);
  } else {  // a valid v1 frame this device does not handle
    rx_error_ = true;
    send_error(seq, kErrUnknownType);
  }
  (void)len;
}

void Device::setpoint(const SetpointFields& sp) {
  ++counters_.setpoints;
  last_good_seq_ = sp.seq;
  if (sp.flags & kFlagClearFaults) {  // before building the reply (§2.1)
    tripped_ = false;
    rx_error_ = false;
    if (!driver_fault_input_) driver_fault_ = false;
    if (!estop_input_) estop_ = false;  // an E-stop still open stays latched
  }
  // the watchdog restarts on every valid SETPOINT, SYNC or not
  armed_ = true;
  starved_ = false;
  last_sp_us_ = now_us_;
  watchdog_us_ = 1000u * (sp.watchdog_ms ? sp.watchdog_ms : kDefaultWatchdogMs);

  // clamp: NaN/inf -> 0 A, outside [0, I_max] -> the nearer bound (§2.1)
  float I = sp.current_A;
  bool clamped = false;
  if (!isfinite(I)) {
    I = 0.0f;
    clamped = true;
  } else if (I < 0.0f) {
    I = 0.0f;
    clamped = true;
  } else if (I > cfg_.I_max_A) {
    I = cfg_.I_max_A;
    clamped = true;
  }
  const bool enable = (sp.flags & kFlagEnable) != 0;

  if (sp.flags & kFlagSync) {  // §6.1: applied and answered at the next tick
    pending_ = true;
    pending_A_ = I;
    pending_enable_ = enable;
    if (n_owed_ == kMaxOwed) {  // the oldest is the one the host has given up on
      for (size_t i = 1; i < kMaxOwed; ++i) owed_[i - 1] = owed_[i];
      --n_owed_;
      ++counters_.sync_overflows;
    }
    owed_[n_owed_++] = Owed{sp.seq, clamped};
    return;
  }
  pending_ = false;  // the newest setpoint wins
  apply(I, enable);
  send_sample(sp.seq, clamped);
}

// --- the tick and the watchdog ----------------------------------------------------

void Device::tick(const RawInputs& raw, uint32_t t_us) {
  now_us_ = t_us;
  ++counters_.ticks;
  driver_fault_input_ = raw.driver_fault;
  if (raw.driver_fault) driver_fault_ = true;
  sense_estop();  // 0 A at this tick, before anything else is applied
  if (pending_) {
    pending_ = false;
    apply(pending_A_, pending_enable_);
  }
  watchdog(t_us);
  drive();

  // latch the measurement
  bool fault = false;
  const float x = to_si(cfg_.x, raw.x_counts, &fault);
  float v = kNaN;
  if (fault) {
    have_x_ = false;  // restart the derivative after the fault
  } else if (v_alpha_ > 0.0f) {
    if (have_x_) {
      const float dxdt = (x - x_prev_) / cfg_.sample_period_s;
      v_filt_ = v_alpha_ * v_filt_ + (1.0f - v_alpha_) * dxdt;
    } else {
      v_filt_ = 0.0f;
    }
    v = v_filt_;
    have_x_ = true;
    x_prev_ = x;
  }
  float F = kNaN;
  uint16_t st = 0;
  if (cfg_.has_load_cell) {
    F = to_si(cfg_.force, raw.force_counts, &fault);
  } else {
    st |= kStatusNoLoadCell;
  }
  if (fault) st |= kStatusSensorFault;
  meas_.seq += 1;  // the number of the measurement (§5), wraps mod 2^32
  meas_.t_dev_us = t_us;
  meas_.x_m = x;
  meas_.v_mps = v;
  meas_.F_N = F;
  meas_.current_A = isfinite(raw.current_monitor_A) ? raw.current_monitor_A : applied_A_;
  meas_status_ = st;

  // the SYNC requests this tick applied are answered with its sample
  for (size_t i = 0; i < n_owed_; ++i) send_sample(owed_[i].echo_seq, owed_[i].clamped);
  n_owed_ = 0;
}

void Device::poll(uint32_t now_us) {
  now_us_ = now_us;
  watchdog(now_us);
}

void Device::watchdog(uint32_t now_us) {
  // modulo-2^32 difference, signed: a tick's time is the one its timer latched,
  // which comes before a setpoint received after the latch but before the main
  // loop served the tick; that setpoint is "in the future" (negative), not
  // 71 minutes old. Once expired it stays so until a setpoint arrives
  // (starved_), so the µs counter wrapping cannot revive an old setpoint.
  if (!armed_ || starved_) return;
  const int32_t since = static_cast<int32_t>(now_us - last_sp_us_);
  if (since >= 0 && static_cast<uint32_t>(since) >= watchdog_us_) {
    starved_ = true;
    pending_ = false;
    if (!tripped_) ++counters_.watchdog_trips;
    tripped_ = true;
    drive();
  }
}

void Device::apply(float current_A, bool enable) {
  cmd_A_ = current_A;
  cmd_enable_ = enable;
  drive();
}

// the E-stop input, live: an opening latches ESTOP (and is counted) at once
void Device::sense_estop() {
  const bool open = io_.estop_open();
  if (open && !estop_input_) ++counters_.estops;
  estop_input_ = open;
  if (open) estop_ = true;
}

// the one place the output is set: 0 A and disabled unless every condition holds
// (the E-stop input is read here, not only at ticks: a SETPOINT or CLEAR_FAULTS
// handled between the input opening and the next tick must not drive the output)
void Device::drive() {
  sense_estop();
  const bool on = armed_ && !starved_ && cmd_enable_ && !driver_fault_ && !estop_;
  const float I = on ? cmd_A_ : 0.0f;
  float counts = I * cfg_.output_counts_per_A + 0.5f;
  if (!(counts > 0.0f)) counts = 0.0f;
  const float full = static_cast<float>(cfg_.output_max_counts);
  if (counts > full) counts = full;
  applied_A_ = I;
  output_on_ = on;
  io_.set_output(static_cast<uint32_t>(counts), on);
}

float Device::to_si(const AnalogChannel& ch, int32_t counts, bool* fault) const {
  if (counts < ch.valid_min || counts > ch.valid_max) *fault = true;
  return static_cast<float>(counts - ch.zero_counts) * ch.si_per_count;
}

// --- replies ------------------------------------------------------------------------

uint16_t Device::status(bool clamped) const {
  uint16_t st = meas_status_;
  if (driver_fault_) st |= kStatusDriverFault;
  if (tripped_) st |= kStatusWatchdogTripped;
  if (output_on_) st |= kStatusOutputEnabled;
  if (clamped) st |= kStatusCurrentClamped;
  if (rx_error_) st |= kStatusRxError;
  if (estop_) st |= kStatusEstop;
  return st;
}

void Device::send_sample(uint32_t echo_seq, bool clamped) {
  SampleFields s = meas_;
  s.echo_seq = echo_seq;
  s.status = status(clamped);
  uint8_t out[kSampleFrame];
  io_.send(out, encode_sample(out, s));
  ++counters_.samples_sent;
}

void Device::send_error(uint32_t echo_seq, uint8_t code, uint8_t detail) {
  uint8_t out[kErrorFrame];
  io_.send(out, encode_error(out, meas_.seq, echo_seq, code, detail));
  ++counters_.errors_sent;
}

}  // namespace mrctl_fw
