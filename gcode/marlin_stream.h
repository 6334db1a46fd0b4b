#pragma once
// The host side of Marlin's line protocol as a state machine, without I/O or clocks: which framed
// line to write next, and what each reply means for it. One line is in flight at a time (the
// "ping-pong" Printrun and OctoPrint use by default): a probe run sends a few short lines per
// press, so the round trip costs little, and one line in flight keeps a resend unambiguous.
//
// Line numbers make every failure safe to retry. A line lost on the way (no ok in time) is written
// again with the same number: if the printer had taken it, it refuses the duplicate ("Line Number
// is not Last Line Number+1") and asks for the next, which acknowledges the first. A garbled line
// is refused ("checksum mismatch") and asked for again ("Resend: N", then an ok that belongs to
// the refusal, not to a line: it is swallowed). After a reboot ("start") the numbering starts over
// with M110 N0, and what was in flight is the caller's to decide about: it may never have run.

#include <cstddef>
#include <cstdint>
#include <deque>
#include <optional>
#include <string>

#include "gcode/marlin_messages.h"

namespace gs360 {

struct MarlinStreamEvent {
  enum class Kind {
    kNone,      // nothing for the caller (a keep-alive, an echo, a swallowed ok, a framing error)
    kAcked,     // the line `sequence` was taken (its ok, or the printer asked for the next one)
    kResend,    // the printer asked for a line again: NextToWrite() has it
    kBusy,      // "echo:busy:": the printer is working on a long command; not a time-out
    kError,     // an error that is not about framing (`text`); the line in flight stays in flight
    kHalted,    // the printer halted (kill(), M112, Klipper's shutdown); nothing more is sent
    kRebooted,  // "start": the board booted; `sequence` is the line in flight (0: none), lost
  };
  Kind kind = Kind::kNone;
  std::uint64_t sequence = 0;
  std::string text;
};

class MarlinStream {
 public:
  // Starts numbering: the first line written is "N0 M110 N0".
  MarlinStream();

  // Queues a command (its comment dropped); returns its sequence number (1, 2, ...). Throws
  // std::invalid_argument as MarlinFrame does for a command that cannot be framed.
  std::uint64_t Queue(std::string_view command);
  // The framed line to write now: nothing while a line waits for its ok, when nothing is queued,
  // or after a halt.
  std::optional<std::string> NextToWrite();
  // One reply from the printer.
  MarlinStreamEvent OnReply(const MarlinMessage& reply);
  // No reply in time: the line in flight, framed again with its own number, to write again (the
  // printer refuses it if it had taken it, and asks for the next); nothing when none is in flight.
  std::optional<std::string> RetryInFlight();
  // To start over on a new connection (a reply "start" does it too): numbering from M110 N0
  // again, the halt forgotten; the queue is kept, the line in flight (if any) is dropped and
  // returned (its sequence).
  std::optional<std::uint64_t> Restart();
  // Drops the queued commands (not the M110 that starts the numbering): after a reboot the
  // caller decides what to send, from a verified position.
  void ClearQueue();

  bool Halted() const { return halted_; }
  // Nothing in flight or queued but the M110 that starts the numbering, or not even that.
  bool Idle() const;
  std::size_t Queued() const;  // commands queued (the stream's own M110 not counted)
  std::uint64_t Resends() const { return resends_; }     // lines the printer asked for again
  std::uint64_t Retries() const { return retries_; }     // lines written again after a time-out
  std::uint64_t StrayOks() const { return stray_oks_; }  // oks that were no line's

 private:
  struct Line {
    long number = 0;
    std::uint64_t sequence = 0;  // 0: the M110 that starts the numbering
    std::string command;
  };
  MarlinStreamEvent Acked();
  MarlinStreamEvent OnResend(long line);

  std::deque<Line> queue_;
  std::optional<Line> in_flight_;
  long next_number_ = 0;
  std::uint64_t next_sequence_ = 1;
  bool write_again_ = false;  // the printer asked for the line in flight again
  int swallow_oks_ = 0;       // oks owed to refusals, not to lines
  bool halted_ = false;
  std::uint64_t resends_ = 0, retries_ = 0, stray_oks_ = 0;
};

}  // namespace gs360
