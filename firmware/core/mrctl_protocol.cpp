// mrctl serial protocol v1, device side (see mrctl_protocol.h, docs/protocol.md).
#include "mrctl_protocol.h"

#include <string.h>

namespace mrctl_fw {

uint16_t crc16_ccitt_false(const uint8_t* p, size_t n) {
  uint16_t crc = 0xFFFF;
  while (n--) {
    crc = static_cast<uint16_t>(crc ^ (static_cast<uint16_t>(*p++) << 8));
    for (int i = 0; i < 8; i++)
      crc = (crc & 0x8000) ? static_cast<uint16_t>((crc << 1) ^ 0x1021) : static_cast<uint16_t>(crc << 1);
  }
  return crc;
}

uint32_t get_u32(const uint8_t* p) {
  return static_cast<uint32_t>(p[0]) | (static_cast<uint32_t>(p[1]) << 8) |
         (static_cast<uint32_t>(p[2]) << 16) | (static_cast<uint32_t>(p[3]) << 24);
}

float get_f32(const uint8_t* p) {
  const uint32_t u = get_u32(p);
  float f;
  memcpy(&f, &u, sizeof f);
  return f;
}

void put_u16(uint8_t* p, uint16_t v) {
  p[0] = static_cast<uint8_t>(v);
  p[1] = static_cast<uint8_t>(v >> 8);
}

void put_u32(uint8_t* p, uint32_t v) {
  for (int i = 0; i < 4; ++i) p[i] = static_cast<uint8_t>(v >> (8 * i));
}

void put_f32(uint8_t* p, float v) {
  static_assert(sizeof(float) == 4, "IEEE-754 binary32 float expected");
  uint32_t u;
  memcpy(&u, &v, sizeof u);
  put_u32(p, u);
}

namespace {

size_t header(uint8_t* out, uint8_t version, uint8_t type, size_t payload_len, uint32_t seq) {
  out[0] = kPreamble0;
  out[1] = kPreamble1;
  out[2] = version;
  out[3] = type;
  out[4] = static_cast<uint8_t>(payload_len);
  put_u32(out + 5, seq);
  return kHeaderSize;
}

// CRC over everything before it, appended little-endian; returns the frame size
size_t finish(uint8_t* out, size_t payload_len) {
  const size_t body = kHeaderSize + payload_len;
  put_u16(out + body, crc16_ccitt_false(out, body));
  return body + kCrcSize;
}

// fixed payload length of a known v1 type, or -1 (unknown or variable)
int fixed_payload_len(uint8_t type) {
  switch (type) {
    case kTypeSetpoint: return static_cast<int>(kSetpointPayload);
    case kTypeSample: return static_cast<int>(kSamplePayload);
    case kTypeError: return static_cast<int>(kErrorPayload);
    case kTypeChannelQuery: return 0;
    default: return -1;
  }
}

}  // namespace

size_t encode_setpoint(uint8_t* out, const SetpointFields& f) {
  uint8_t* p = out + header(out, kVersion, kTypeSetpoint, kSetpointPayload, f.seq);
  put_f32(p, f.current_A);
  p[4] = f.flags;
  p[5] = f.watchdog_ms;
  return finish(out, kSetpointPayload);
}

size_t encode_sample(uint8_t* out, const SampleFields& f) {
  uint8_t* p = out + header(out, kVersion, kTypeSample, kSamplePayload, f.seq);
  put_u32(p + 0, f.echo_seq);
  put_u32(p + 4, f.t_dev_us);
  put_f32(p + 8, f.x_m);
  put_f32(p + 12, f.v_mps);
  put_f32(p + 16, f.F_N);
  put_f32(p + 20, f.current_A);
  put_u16(p + 24, f.status);
  return finish(out, kSamplePayload);
}

size_t encode_error(uint8_t* out, uint32_t seq, uint32_t echo_seq, uint8_t code, uint8_t detail,
                    uint8_t version) {
  uint8_t* p = out + header(out, version, kTypeError, kErrorPayload, seq);
  put_u32(p, echo_seq);
  p[4] = code;
  p[5] = detail;
  return finish(out, kErrorPayload);
}

size_t encode_channel_list(uint8_t* out, size_t cap, uint32_t seq, uint32_t echo_seq, const char* names) {
  const size_t n = strlen(names);
  const size_t payload = 4 + n;
  if (payload > kMaxPayload || kHeaderSize + payload + kCrcSize > cap) return 0;
  uint8_t* p = out + header(out, kVersion, kTypeChannelList, payload, seq);
  put_u32(p, echo_seq);
  memcpy(p + 4, names, n);
  return finish(out, payload);
}

SetpointFields decode_setpoint(const uint8_t* frame) {
  SetpointFields f;
  f.seq = get_u32(frame + 5);
  f.current_A = get_f32(frame + kHeaderSize);
  f.flags = frame[kHeaderSize + 4];
  f.watchdog_ms = frame[kHeaderSize + 5];
  return f;
}

// --- Receiver -----------------------------------------------------------------

void Receiver::discard(size_t n) {
  if (n == 0) return;
  if (n > len_) n = len_;
  memmove(buf_, buf_ + n, len_ - n);
  len_ -= n;
  bytes_discarded += static_cast<uint32_t>(n);
  sink_.on_discard();
}

Receiver::Kind Receiver::probe(size_t i, size_t* end) const {
  if (len_ - i < 5) return kIncomplete;
  const uint8_t version = buf_[i + 2];
  const uint8_t plen = buf_[i + 4];
  if (version == 0 || plen > kMaxPayload) return kBadHeader;
  if (version == kVersion) {
    const int expected = fixed_payload_len(buf_[i + 3]);
    if (expected >= 0 && plen != expected) return kBadHeader;
  }
  const size_t e = i + kHeaderSize + plen + kCrcSize;
  *end = e;
  if (e > len_) return kIncomplete;
  const uint16_t rx = static_cast<uint16_t>(buf_[e - 2] | (buf_[e - 1] << 8));
  return crc16_ccitt_false(buf_ + i, e - kCrcSize - i) == rx ? kOk : kBadCrc;
}

void Receiver::push(uint8_t byte) {
  if (len_ >= sizeof buf_) discard(1);  // cannot happen: process() keeps < one frame
  buf_[len_++] = byte;
  process();
}

void Receiver::process() {
  while (len_ > 0) {
    // 1. find the next preamble; bytes before it are noise
    size_t i = 0;
    while (i + 1 < len_ && !(buf_[i] == kPreamble0 && buf_[i + 1] == kPreamble1)) ++i;
    if (i + 1 >= len_) {  // none: keep a trailing A5, it may start one
      discard(buf_[len_ - 1] == kPreamble0 ? len_ - 1 : len_);
      return;
    }
    discard(i);
    size_t end = 0;
    switch (probe(0, &end)) {
      case kOk:
        ++frames;
        sink_.on_frame(buf_, end);
        memmove(buf_, buf_ + end, len_ - end);
        len_ -= end;
        break;
      case kIncomplete: {
        // 5. a complete valid frame later in the buffer wins over the candidate
        size_t j = 1;
        for (; j + 1 < len_; ++j) {
          size_t e2 = 0;
          if (buf_[j] == kPreamble0 && buf_[j + 1] == kPreamble1 && probe(j, &e2) == kOk) break;
        }
        if (j + 1 >= len_) return;  // wait for more bytes
        discard(j);
        break;
      }
      case kBadHeader:
        ++header_errors;
        discard(1);  // 4. drop ONE byte and rescan
        break;
      case kBadCrc:
        ++crc_errors;
        if (buf_[2] == kVersion && buf_[3] == kTypeSetpoint) sink_.on_setpoint_crc_error();
        discard(1);
        break;
    }
  }
}

}  // namespace mrctl_fw
