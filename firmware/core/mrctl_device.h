// The device side of mrctl's serial protocol (docs/protocol.md), board-neutral:
// the sampling tick, setpoints, SYNC pacing, the millisecond watchdog, status
// bits and every reply. A board file supplies raw ADC counts at each tick of
// its hardware timer, the received bytes, and a DeviceIo that moves bytes out
// and sets the driver output; everything the protocol defines happens here.
//
// Single context: call receive(), tick() and poll() from one context (the
// board's main loop; its timer ISR only latches the ADC readings). No dynamic
// allocation; the object is a few hundred bytes.
#pragma once

#include <stddef.h>
#include <stdint.h>

#include "mrctl_protocol.h"

namespace mrctl_fw {

// ADC counts -> SI: value = (counts - zero_counts) * si_per_count; counts
// outside [valid_min, valid_max] (a rail, an open wire) set SENSOR_FAULT.
struct AnalogChannel {
  int32_t zero_counts;
  float si_per_count;  // m per count (LVDT) or N per count (load cell)
  int32_t valid_min;
  int32_t valid_max;
};

struct DeviceConfig {
  AnalogChannel x;            // LVDT, metres
  AnalogChannel force;        // load cell, newtons
  bool has_load_cell;         // false: F_N = NaN and NO_LOAD_CELL
  float sample_period_s;      // the hardware timer's period (1e-3 at 1 kHz)
  float velocity_cutoff_hz;   // first-order filtered derivative of x; <= 0: v = NaN (host observer)
  float I_max_A;              // setpoints are clamped to [0, I_max_A]
  float output_counts_per_A;  // DAC/PWM counts per ampere of driver output
  uint32_t output_max_counts;  // the DAC/PWM's full scale
};

// What a board samples at each tick of its timer.
struct RawInputs {
  int32_t x_counts;
  int32_t force_counts;
  bool driver_fault;          // the driver's fault output is active
  float current_monitor_A;    // the driver's measured current, A; NaN = not fitted
};

// The board's side: bytes to the host, the driver's control input, and the
// E-stop input.
class DeviceIo {
 public:
  virtual void send(const uint8_t* data, size_t n) = 0;
  // counts for the DAC/PWM (0 = 0 A), and the driver's enable input
  virtual void set_output(uint32_t counts, bool enable) = 0;
  // the E-stop / interlock input now: true = open (the board applies its
  // polarity). Read at every tick and before every output change, so no
  // setpoint between two ticks can drive the output while it is open.
  virtual bool estop_open() = 0;

 protected:
  ~DeviceIo() = default;
};

struct DeviceCounters {
  uint32_t ticks;
  uint32_t setpoints;
  uint32_t samples_sent;
  uint32_t errors_sent;
  uint32_t watchdog_trips;
  uint32_t sync_overflows;  // SYNC replies dropped (the oldest): more than kMaxOwed within one tick
  uint32_t estops;          // times the E-stop input opened
};

class Device : private FrameSink {
 public:
  static constexpr size_t kMaxOwed = 4;  // SYNC replies owed to the next tick

  Device(const DeviceConfig& cfg, DeviceIo& io);

  // bytes from the host, received at device time now_us
  void receive(const uint8_t* data, size_t n, uint32_t now_us);
  // the sampling tick at device time t_us: applies a pending SYNC setpoint,
  // latches the measurement, answers the SYNC requests owed to this tick
  void tick(const RawInputs& raw, uint32_t t_us);
  // between ticks (call often): the setpoint watchdog
  void poll(uint32_t now_us);

  float applied_A() const { return applied_A_; }
  bool output_enabled() const { return output_on_; }
  bool watchdog_tripped() const { return tripped_; }
  bool estop_latched() const { return estop_; }
  const DeviceCounters& counters() const { return counters_; }
  const Receiver& receiver() const { return rx_; }

 private:
  struct Owed {
    uint32_t echo_seq;
    bool clamped;
  };

  void on_frame(const uint8_t* frame, size_t len) override;
  void on_setpoint_crc_error() override;
  void on_discard() override { rx_error_ = true; }

  void setpoint(const SetpointFields& sp);
  void apply(float current_A, bool enable);
  void watchdog(uint32_t now_us);
  void drive();
  void sense_estop();
  uint16_t status(bool clamped) const;
  void send_sample(uint32_t echo_seq, bool clamped);
  void send_error(uint32_t echo_seq, uint8_t code, uint8_t detail = 0);
  float to_si(const AnalogChannel& ch, int32_t counts, bool* fault) const;

  DeviceConfig cfg_;
  DeviceIo& io_;
  Receiver rx_;
  DeviceCounters counters_ = {};
  uint32_t now_us_ = 0;

  // the latest completed measurement (what every reply carries)
  SampleFields meas_ = {};
  uint16_t meas_status_ = 0;  // SENSOR_FAULT, NO_LOAD_CELL of that measurement
  float x_prev_ = 0.0f;
  float v_filt_ = 0.0f;
  bool have_x_ = false;
  float v_alpha_ = 0.0f;

  // setpoint and output
  float cmd_A_ = 0.0f;        // clamped setpoint in force
  bool cmd_enable_ = false;
  bool pending_ = false;      // a SYNC setpoint waiting for the next tick
  float pending_A_ = 0.0f;
  bool pending_enable_ = false;
  Owed owed_[kMaxOwed] = {};
  size_t n_owed_ = 0;
  float applied_A_ = 0.0f;
  bool output_on_ = false;

  // watchdog: from power-up 0 A until the first valid setpoint
  bool armed_ = false;        // a valid setpoint has arrived
  bool starved_ = false;      // expired, setpoints absent (0 A)
  uint32_t last_sp_us_ = 0;
  uint32_t watchdog_us_ = kDefaultWatchdogMs * 1000u;

  // latched status
  bool tripped_ = false;      // WATCHDOG_TRIPPED
  bool rx_error_ = false;     // RX_ERROR
  bool driver_fault_ = false; // DRIVER_FAULT (latched)
  bool driver_fault_input_ = false;  // the driver's fault line at the last tick
  bool estop_ = false;        // ESTOP (latched: 0 A until CLEAR_FAULTS once the input closed)
  bool estop_input_ = false;  // the E-stop input when last read
  uint32_t last_good_seq_ = 0;
};

}  // namespace mrctl_fw
