#include "gcode/marlin_stream.h"

#include <utility>

namespace gs360 {

MarlinStream::MarlinStream() {
  Restart();
}

std::uint64_t MarlinStream::Queue(std::string_view command) {
  MarlinFrame(0, command);  // throws for a command that cannot be framed, before it is queued
  const std::string_view bare = command.substr(0, command.find(';'));
  queue_.push_back({0, next_sequence_, std::string(bare)});
  return next_sequence_++;
}

std::optional<std::string> MarlinStream::NextToWrite() {
  if (halted_) return std::nullopt;
  if (in_flight_) {
    if (!write_again_) return std::nullopt;
    write_again_ = false;
    return MarlinFrame(in_flight_->number, in_flight_->command);
  }
  if (queue_.empty()) return std::nullopt;
  in_flight_ = std::move(queue_.front());
  queue_.pop_front();
  in_flight_->number = next_number_++;
  return MarlinFrame(in_flight_->number, in_flight_->command);
}

MarlinStreamEvent MarlinStream::Acked() {
  MarlinStreamEvent e{MarlinStreamEvent::Kind::kAcked, in_flight_->sequence, {}};
  in_flight_.reset();
  write_again_ = false;
  // The M110 that starts the numbering is the stream's own: nothing for the caller.
  if (e.sequence == 0) e.kind = MarlinStreamEvent::Kind::kNone;
  return e;
}

MarlinStreamEvent MarlinStream::OnResend(long line) {
  ++resends_;
  ++swallow_oks_;  // the ok that follows the request belongs to the refusal
  if (in_flight_ && line == in_flight_->number) {
    write_again_ = true;
    return {MarlinStreamEvent::Kind::kResend, in_flight_->sequence, {}};
  }
  // Asked for the line after the one in flight: it had been taken (a retry after a lost ok).
  if (in_flight_ && line == in_flight_->number + 1) return Acked();
  if (!in_flight_ && line == next_number_) return {};  // nothing sent since: nothing to resend
  return {MarlinStreamEvent::Kind::kError, in_flight_ ? in_flight_->sequence : 0,
          "the printer asks for line " + std::to_string(line) + " again, which was " +
              (line < next_number_ ? "taken already" : "never sent") +
              ": the numbering is out of step (restart it with M110)"};
}

MarlinStreamEvent MarlinStream::OnReply(const MarlinMessage& reply) {
  using Kind = MarlinStreamEvent::Kind;
  switch (reply.kind) {
    case MarlinMessageKind::kOk:
      if (swallow_oks_ > 0) {
        --swallow_oks_;
        return {};
      }
      // An ok while the line in flight waits to be written again, or for a line before it
      // (ADVANCED_OK numbers it), is not this line's.
      if (!in_flight_ || write_again_ || (reply.line && *reply.line != in_flight_->number)) {
        ++stray_oks_;
        return {};
      }
      return Acked();
    case MarlinMessageKind::kResend:
      return OnResend(*reply.line);
    case MarlinMessageKind::kBusy:
      return {Kind::kBusy, in_flight_ ? in_flight_->sequence : 0, reply.text};
    case MarlinMessageKind::kError:
      return {Kind::kError, in_flight_ ? in_flight_->sequence : 0, reply.text};
    case MarlinMessageKind::kHalted:
      halted_ = true;
      return {Kind::kHalted, in_flight_ ? in_flight_->sequence : 0, reply.text};
    case MarlinMessageKind::kStart: {
      const std::optional<std::uint64_t> lost = Restart();
      return {Kind::kRebooted, lost.value_or(0), {}};
    }
    default:
      return {};  // framing errors (a Resend follows), echoes, reports: the caller's to log
  }
}

bool MarlinStream::Idle() const {
  return !in_flight_ && (queue_.empty() || (queue_.size() == 1 && queue_.front().sequence == 0));
}

std::size_t MarlinStream::Queued() const {
  const bool numbering = !queue_.empty() && queue_.front().sequence == 0;
  return queue_.size() - (numbering ? 1 : 0);
}

void MarlinStream::ClearQueue() {
  const bool numbering = !queue_.empty() && queue_.front().sequence == 0;
  queue_.clear();
  if (numbering) queue_.push_front({0, 0, "M110 N0"});
}

std::optional<std::string> MarlinStream::RetryInFlight() {
  if (halted_ || !in_flight_) return std::nullopt;
  ++retries_;
  write_again_ = false;
  return MarlinFrame(in_flight_->number, in_flight_->command);
}

std::optional<std::uint64_t> MarlinStream::Restart() {
  std::optional<std::uint64_t> lost;
  if (in_flight_ && in_flight_->sequence != 0) lost = in_flight_->sequence;
  in_flight_.reset();
  write_again_ = false;
  swallow_oks_ = 0;
  halted_ = false;
  next_number_ = 0;
  // Drop an M110 still queued from before: one starts the numbering.
  if (!queue_.empty() && queue_.front().sequence == 0) queue_.pop_front();
  queue_.push_front({0, 0, "M110 N0"});
  return lost;
}

}  // namespace gs360
