// A simulated sensor source for the host build: what the Teensy's ADC would
// read on a shaker bench, so mrctl can run against the firmware core on a pty.
//
// Deliberately simple, not a damper model to identify against:
//   x(t)   = A sin(2π f t)                              (the shaker, m)
//   I_coil : first-order lag tau_s behind the applied current (driver + coil)
//   F      = (c0 + cI·I_coil)·v + (F0 + FI·I_coil)·tanh(v / v0)  (N)
// so the force grows with the coil current and the loop has something to
// close. The defaults are loosely the size of the paper's Table I damper
// (mrctl's `parameters: table1`) below 0.6 A: ~3 N and 15 N·s/m at 0 A,
// +60 N and +100 N·s/m per ampere, an ideal driver (tau 0). The readings go through the board's own calibration backwards
// (SI -> volts -> 12-bit counts, clamped to the ADC's range), so the core sees
// the same quantisation as on the board.
#pragma once

#include <math.h>
#include <stdint.h>

#include "mrctl_device.h"

namespace host {

struct SimParams {
  double amplitude_m = 0.010;
  double frequency_hz = 1.0;
  double c0_Ns_per_m = 15.0;      // passive viscous damping
  double cI_Ns_per_mA = 100.0;    // extra damping per ampere
  double F0_N = 3.0;              // friction-like force at 0 A
  double FI_N_per_A = 60.0;       // friction-like force per ampere
  double v0_mps = 0.02;           // smoothing velocity of the friction term
  double tau_s = 0.0;             // driver + coil lag
  int32_t adc_max_counts = 4095;
};

class SimSource {
 public:
  SimSource(const SimParams& p, const mrctl_fw::DeviceConfig& cfg) : p_(p), cfg_(cfg) {}

  // the readings at time t_s (s), with `applied_A` the device output since the last call
  mrctl_fw::RawInputs sample(double t_s, double applied_A) {
    const double dt = t_s - t_prev_;
    t_prev_ = t_s;
    if (dt > 0 && p_.tau_s > 0)
      I_coil_ += (applied_A - I_coil_) * (1.0 - exp(-dt / p_.tau_s));
    else
      I_coil_ = applied_A;
    const double w = 2.0 * M_PI * p_.frequency_hz;
    x_m = p_.amplitude_m * sin(w * t_s);
    v_mps = p_.amplitude_m * w * cos(w * t_s);
    F_N = (p_.c0_Ns_per_m + p_.cI_Ns_per_mA * I_coil_) * v_mps + (p_.F0_N + p_.FI_N_per_A * I_coil_) * tanh(v_mps / p_.v0_mps);
    mrctl_fw::RawInputs raw;
    raw.x_counts = counts(cfg_.x, x_m);
    raw.force_counts = counts(cfg_.force, F_N);
    raw.driver_fault = false;
    raw.current_monitor_A = NAN;
    return raw;
  }

  double x_m = 0, v_mps = 0, F_N = 0;  // the true values of the last sample

 private:
  int32_t counts(const mrctl_fw::AnalogChannel& ch, double value) const {
    double c = value / ch.si_per_count + ch.zero_counts;
    c = c < 0 ? 0 : (c > p_.adc_max_counts ? p_.adc_max_counts : c);
    return static_cast<int32_t>(lround(c));
  }

  SimParams p_;
  mrctl_fw::DeviceConfig cfg_;
  double t_prev_ = 0;
  double I_coil_ = 0;
};

}  // namespace host
