#pragma once
// GRBL 1.1 streaming client: character counting, real-time commands, status polling, alarms,
// resets, reconnects, and the press synchronisation rule of the calibration run.
//
// Protocol facts this relies on (gnea/grbl doc/markdown/interface.md):
// - `ok` means a line was parsed and queued, not executed; `error:N` means it was discarded.
// - The bytes of unanswered lines (each line + '\n') must fit the firmware's serial RX buffer
//   (128 on classic GRBL; the real size is read from `$I`'s `[OPT:codes,blocks,bytes]`).
// - Real-time bytes (`?` `!` `~` 0x18) are picked off before the buffer and bypass the count.
// - `ALARM:N` may arrive before the `ok`/`error` of the line that caused it.
// - The welcome line follows every reset and voids everything in flight.
// - The `ok` of `G4 P<s>` arrives only after all earlier motion finished and the dwell elapsed:
//   the sync point of a press. Take the frame after WaitForOk() returns (frame timestamp later
//   than the reply's received_at), and only then Send() the retract.
//
// Threads: the client owns a reader thread (parses every line, resolves replies) and a status
// poller (<= 5 Hz). Every public method is thread-safe, except that Connect/Reconnect/
// Disconnect must not be called from a message listener (they join the reader thread).
// Positions are machine coordinates in mm (GRBL MPos, $13=0). Times are host steady_clock.
//
// Expected outcomes are statuses (GrblReply kinds, GrblWaitResult, GrblVerifyResult);
// exceptions are for set-up errors: Connect() throws GrblError / TransportError, Send() throws
// std::invalid_argument for a line that can never be sent.

#include <chrono>
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <functional>
#include <future>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include <Eigen/Core>

#include "gcode/grbl_messages.h"
#include "gcode/transport.h"

namespace gs360 {

// Set-up failure talking to the controller (no welcome, no answer to $I, ...).
class GrblError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

enum class GrblReplyKind {
  kOk,            // "ok": parsed and queued
  kError,         // "error:N": discarded by the firmware; error_code = N
  kReset,         // void: the controller reset (welcome line / SoftReset) before replying
  kRefused,       // never sent: alarm, reset pending, position not trusted, not connected
  kDisconnected,  // the transport vanished before the reply
  kClosed,        // the client was closed (Disconnect / destructor) before the reply
  kTimeout,       // only from waits: no reply yet within the timeout (the line is still pending)
};
std::string_view GrblReplyKindName(GrblReplyKind kind);

struct GrblReply {
  GrblReplyKind kind = GrblReplyKind::kTimeout;
  std::string line;
  std::uint64_t sequence = 0;  // 1, 2, ... in Send() order
  int error_code = 0;          // kError
  // ALARM:N that arrived while this line was the oldest unanswered one (GRBL prints the alarm
  // before the ok/error of the line that caused it). The line still gets its own kind.
  std::optional<int> alarm_code;
  // Feedback lines ([VER:..], [OPT:..], $N=v, [MSG:..], [GC:..], [G54:..], ...) received while
  // this line was the oldest unanswered one: the output of $I, $$, $#, $G.
  std::vector<std::string> messages;
  std::string detail;  // error / alarm text, or why the line was refused or voided
  std::chrono::steady_clock::time_point sent_at{};      // bytes handed to the transport
  std::chrono::steady_clock::time_point received_at{};  // reply bytes read from the transport

  bool Ok() const { return kind == GrblReplyKind::kOk; }
  std::string Describe() const;
};

// A line's future reply. Cheap to copy; all copies see the same reply.
class GrblHandle {
 public:
  GrblHandle() = default;
  bool Valid() const { return future_.valid(); }
  std::uint64_t Sequence() const { return sequence_; }
  const std::string& Line() const { return line_; }
  // True once the reply (or the void/refusal) is known.
  bool Done() const;
  // The reply, or a kTimeout reply when none arrived within `timeout`.
  GrblReply Wait(std::chrono::milliseconds timeout) const;

 private:
  friend class GrblClient;
  std::shared_future<GrblReply> future_;
  std::uint64_t sequence_ = 0;
  std::string line_;
};

struct GrblClientOptions {
  // After opening, how long to wait for the welcome before sending a soft reset (0x18); an
  // Arduino resets when the port opens and boots in ~1-2 s.
  std::chrono::milliseconds welcome_timeout{2500};
  // How long to wait for the welcome after a soft reset.
  std::chrono::milliseconds reset_timeout{3000};
  // Replies to $I and $$ during Connect.
  std::chrono::milliseconds query_timeout{3000};
  // Reply to $H (the homing cycle runs before the ok).
  std::chrono::milliseconds homing_timeout{120000};
  // The least time between two '?' the client sends (poller, QueryStatus, WaitIdle), 1..1000 ms.
  // GRBL on an AVR asks for at most 5 Hz; grblHAL and the virtual CNC answer much faster, and at
  // instant motion a run otherwise spends most of each probe waiting for its turn to ask.
  std::chrono::milliseconds status_min_interval{200};
  // Status poll period; 0 disables the poller, otherwise at least status_min_interval.
  std::chrono::milliseconds status_poll_interval{200};
  // RX buffer size assumed until `$I` reports one (classic GRBL).
  int default_rx_buffer_bytes = 128;
  // Bytes kept free below the RX size: GRBL's ring buffer holds size - 1 bytes.
  int rx_reserve_bytes = 1;
  // Refuse motion lines (axis words, G28/G30, $J=) while the position is not trusted (after
  // connect, reset, reconnect, a position-losing alarm) until Home(), VerifyPosition() or
  // MarkPositionTrusted().
  bool guard_motion = true;
  // Reconnect retry backoff: doubles from initial to max.
  std::chrono::milliseconds reconnect_backoff_initial{100};
  std::chrono::milliseconds reconnect_backoff_max{2000};

  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

struct GrblMachineInfo {
  std::string firmware;                  // welcome: "Grbl", "GrblHAL"
  std::string version;                   // welcome: "1.1h"
  std::string build;                     // [VER:] "1.1h.20190830"
  std::string option_codes;              // [OPT:] letters
  int planner_blocks = 0;                // [OPT:] planner blocks, 0 if not reported
  int rx_buffer_bytes = 0;               // the RX size the client counts against
  bool rx_buffer_from_firmware = false;  // true when $I reported it
  std::map<int, double> settings;        // $$ numeric values ($110-$112 mm/min, $120-$122 mm/s^2)
  // The controller stood in a feed hold when the port opened and the handshake ended it with a
  // soft reset (a completed hold keeps the position; the held lines are dropped).
  bool ended_feed_hold = false;

  std::optional<double> Setting(int number) const;
};

struct GrblStatusSample {
  GrblStatusReport status;
  // MPos, or WPos + the latest WCO; nullopt when unknown.
  std::optional<Eigen::Vector3d> machine_position;
  std::chrono::steady_clock::time_point received_at{};
};

// kHeld: the controller stands in a completed feed hold (Hold:0), which only a cycle start (~) or
// a soft reset ends: waiting longer would not make it idle.
enum class GrblWaitResult { kIdle, kTimeout, kAlarm, kDisconnected, kHeld };
std::string_view GrblWaitResultName(GrblWaitResult result);

struct GrblVerifyResult {
  bool ok = false;
  std::string detail;
  std::optional<Eigen::Vector3d> reported;  // machine position read from the status report
  double error_mm = 0.0;                    // |reported - expected|
};

struct GrblClientStats {
  std::uint64_t lines_sent = 0;
  std::uint64_t replies = 0;
  std::uint64_t status_requests = 0;  // '?' bytes sent
  std::uint64_t status_reports = 0;
  std::uint64_t resets = 0;  // welcome lines seen
  std::uint64_t alarms = 0;
  std::uint64_t unknown_lines = 0;
  std::uint64_t stray_replies = 0;  // ok / error:N with no line in flight
  std::size_t max_in_flight_bytes = 0;
};

class GrblClient {
 public:
  // Opens the transport for Connect() and for every Reconnect(); may throw TransportError.
  using TransportFactory = std::function<std::unique_ptr<Transport>()>;
  using MessageListener = std::function<void(const GrblMessage&)>;

  explicit GrblClient(TransportFactory factory, GrblClientOptions options = {});
  // A client whose transport is OpenTransport(uri, transport_options) (for "serial:VID:PID" the
  // device is looked up again at every reconnect).
  static std::unique_ptr<GrblClient> ForUri(const std::string& uri,
                                            const TransportOptions& transport_options = {},
                                            const GrblClientOptions& options = {});
  // Stops the threads and closes the transport; pending handles resolve as kClosed.
  ~GrblClient();
  GrblClient(const GrblClient&) = delete;
  GrblClient& operator=(const GrblClient&) = delete;

  // Opens the transport, discards what an earlier session left in it, waits for the welcome
  // (without one: a controller that answers a status query is taken as it is, still running and
  // perhaps moving; only one that does not gets a soft reset), reads `$I` (RX buffer size,
  // default 128 when absent) and `$$` (settings). The position is not trusted afterwards: Home()
  // or VerifyPosition(). Throws TransportError (cannot open) or GrblError (no welcome, no reply).
  GrblMachineInfo Connect();
  // After a disconnect (or at any time): closes the current transport, then retries the factory
  // with backoff until a port answers the handshake or `timeout` expires. The device may come
  // back under another name if the factory resolves it (OpenTransport("serial:VID:PID")).
  // Returns false on timeout. The position is not trusted afterwards.
  bool Reconnect(std::chrono::milliseconds timeout);
  bool Reconnect(TransportFactory factory, std::chrono::milliseconds timeout);
  // Same with OpenTransport(uri, transport_options) as the factory from now on.
  bool Reconnect(const std::string& uri, const TransportOptions& transport_options,
                 std::chrono::milliseconds timeout);
  // Closes the transport; pending handles resolve as kClosed.
  void Disconnect();

  bool Connected() const;
  GrblMachineInfo MachineInfo() const;
  const GrblClientOptions& Options() const { return options_; }

  // Queues a line (no '\n') for streaming and returns its handle at once. Lines are written in
  // order as soon as the RX buffer has room (character counting); settings writes ($x=..., $N,
  // G10 L2/L20, G28.1/G30.1) and other '$' system commands are sent only when nothing else is
  // in flight, and nothing follows them until their reply. Refused (handle already resolved as
  // kRefused / kDisconnected) while alarmed (except '$' commands), while a critical alarm waits
  // for SoftReset(), while a reset's welcome is pending, when not connected, and for motion
  // while the position is not trusted.
  // Throws std::invalid_argument for a line with '\n', '\r', real-time characters (? ! ~ 0x18,
  // bytes >= 0x80) or longer than the RX buffer.
  GrblHandle Send(std::string_view line);

  // $H: homing cycle, waits homing_timeout. On ok: alarm cleared, position trusted.
  GrblReply Home();
  // $X: alarm unlock, waits query_timeout. Does not make the position trusted.
  GrblReply Unlock();

  // Real-time commands, written at once regardless of the RX count. False if not connected.
  bool FeedHold();    // '!': decelerate to a stop (pause)
  bool CycleStart();  // '~': resume
  // 0x18. Lines not yet written resolve as kReset at once and new lines are refused until the
  // welcome arrives. Replies that arrive before the welcome still resolve the oldest lines in
  // flight (GRBL answers the line it was executing, e.g. a soft-limit line after the reset that
  // ends its critical alarm); the welcome voids the rest. Returns true when the welcome arrived
  // within reset_timeout (otherwise everything in flight is void and new lines stay refused
  // until Reconnect()).
  bool SoftReset();

  // Waits for the handle's reply. For the sync rule: when kind == kOk, received_at is the host
  // time the `ok` was read; a frame taken after the return is taken after the motion finished.
  GrblReply WaitForOk(const GrblHandle& handle, std::chrono::milliseconds timeout) const;

  // The most recent status report (from the poller or a query).
  std::optional<GrblStatusSample> LatestStatus() const;
  // Sends '?' (respecting the rate limit) and waits for a report received after it.
  std::optional<GrblStatusSample> QueryStatus(std::chrono::milliseconds timeout);
  // Waits until nothing is queued or in flight and two consecutive fresh reports say Idle; kHeld
  // as soon as a report says the controller stands in a completed feed hold.
  GrblWaitResult WaitIdle(std::chrono::milliseconds timeout);
  // The latest report says Hold:0 (or Hold without a substate): stopped in a feed hold, by '!'
  // from a host, a hold button, or a '!' that noise made of another byte.
  bool Held() const;
  // WaitIdle, then compares the reported machine position with `expected_mpos` (mm). On success
  // the position becomes trusted.
  GrblVerifyResult VerifyPosition(const Eigen::Vector3d& expected_mpos, double tolerance_mm,
                                  std::chrono::milliseconds timeout);

  bool PositionTrusted() const;
  // `ok` / `error:N` replies with no line in flight since the last welcome (or Connect()): the
  // controller executed lines that the host had counted void (sent while it was restarting), so
  // where it stands cannot be told from what was sent.
  std::uint64_t StrayRepliesSinceWelcome() const;
  // For machines without homing whose operator vouches for the position.
  void MarkPositionTrusted();
  bool Alarmed() const;
  // A critical alarm (hard / soft limit: [MSG:Reset to continue]) blocks GRBL until SoftReset().
  bool ResetRequired() const;
  std::optional<int> LastAlarm() const;

  std::size_t InFlightLines() const;
  std::size_t InFlightBytes() const;
  std::size_t QueuedLines() const;
  // The byte budget of unanswered lines: RX size - rx_reserve_bytes.
  std::size_t StreamCapacity() const;
  GrblClientStats Stats() const;

  // Called on the reader thread for every parsed line, after the client's own handling.
  void SetMessageListener(MessageListener listener);

 private:
  struct LineState;

  GrblMachineInfo Handshake();
  // During the handshake, without a welcome: true when the controller answers a status query.
  bool Running(const std::string& what);
  // Running() found it in a feed hold: waits for Hold:0, then a soft reset. False if not held.
  bool EndFeedHold(const std::string& what);
  // After Running(): waits until nothing has arrived for `quiet` (at most `limit`), then forgets
  // every reply and status report received so far. A controller that did not reset may still
  // send what an earlier session asked for (its oks, its status reports) after the port opens;
  // taken as answers, they would match this session's lines or report a stale position.
  void DiscardEarlierSessionReplies(std::chrono::milliseconds quiet,
                                    std::chrono::milliseconds limit);
  void StartThreads();
  void StopThreads();
  void ReaderLoop(Transport* transport);
  void PollLoop();
  // Handshake's steps: the session's state reset (returns the transport's description); the
  // bytes already waiting (an earlier session's dropped, a welcome kept); the welcome awaited
  // (or a running controller taken as it is, its feed hold ended: returns whether one was; or a
  // soft reset); a query that must be answered; the machine's info completed.
  std::string BeginSession(std::uint64_t* resets_before);
  void FeedPendingInput(const std::string& what);
  bool AwaitWelcome(const std::string& what, std::uint64_t resets_before);
  void Query(const std::string& line, const std::string& what);
  GrblMachineInfo FinishHandshake(const std::string& what, bool ended_hold);
  void HandleLine(const std::string& text, std::chrono::steady_clock::time_point t);
  // HandleLine's cases, under mu_: an ok or error (resolves the oldest line in flight), an
  // alarm, the welcome line of a reset, a status report, and what informs (messages, $I, $$).
  void HandleReplyLocked(const GrblMessage& msg, std::chrono::steady_clock::time_point t);
  void HandleAlarmLocked(const GrblMessage& msg);
  void HandleWelcomeLocked(const GrblMessage& msg);
  void HandleStatusLocked(const GrblMessage& msg, std::chrono::steady_clock::time_point t);
  void HandleInfoLocked(const GrblMessage& msg);
  // The following *Locked helpers require mu_.
  void PumpLocked();
  void ResolveLocked(const std::shared_ptr<LineState>& line, GrblReplyKind kind, std::string detail,
                     std::chrono::steady_clock::time_point t);
  void VoidAllLocked(GrblReplyKind kind, const std::string& detail);
  void RefuseQueuedNonSystemLocked(const std::string& detail);
  void TransportLostLocked(const std::string& why);
  void AttachMessageLocked(const std::string& raw);
  bool WriteRealtime(char c);
  // Sends '?' when the 5 Hz budget allows; if `wait`, sleeps until it does. Returns the send
  // time, or nullopt (not sent).
  std::optional<std::chrono::steady_clock::time_point> RequestStatus(bool wait);
  std::size_t CapacityLocked() const;

  GrblClientOptions options_;
  TransportFactory factory_;

  mutable std::mutex mu_;  // state below; lock order: mu_ before write_mu_
  std::condition_variable cv_;
  std::mutex write_mu_;  // serialises transport writes
  std::mutex status_request_mu_;
  std::chrono::steady_clock::time_point last_status_request_{};

  std::unique_ptr<Transport> transport_;  // replaced only while the threads are stopped
  std::thread reader_;
  std::thread poller_;
  bool stop_ = false;

  bool connected_ = false;
  bool awaiting_welcome_ = true;
  bool alarmed_ = false;
  bool reset_required_ = false;  // [MSG:Reset to continue]
  bool trusted_ = false;
  std::uint64_t stray_since_welcome_ = 0;
  std::optional<int> last_alarm_;
  std::uint64_t next_sequence_ = 0;
  std::deque<std::shared_ptr<LineState>> queue_;      // accepted, not yet written
  std::deque<std::shared_ptr<LineState>> in_flight_;  // written, unanswered
  std::size_t in_flight_bytes_ = 0;
  int rx_buffer_bytes_ = 128;
  GrblMachineInfo info_;
  std::optional<GrblStatusSample> latest_status_;
  std::chrono::steady_clock::time_point last_rx_{};  // when the reader last got bytes
  std::optional<Eigen::Vector3d> last_wco_;
  GrblClientStats stats_;
  GrblLineSplitter splitter_;  // reader thread only
  std::shared_ptr<MessageListener> listener_;
};

// --- Press sequence G-code -------------------------------------------------------------------

// One press of the calibration run, in machine coordinates (mm) when machine_coordinates is
// true (each move carries G53), else in the active work coordinates.
struct PressMotion {
  Eigen::Vector3d approach = Eigen::Vector3d::Zero();  // outside the gel, on the normal
  Eigen::Vector3d press = Eigen::Vector3d::Zero();     // ball centre at full depth
  double press_feed_mm_min = 60.0;                     // slow feed from approach to press
  double dwell_s = 0.3;                                // settle time at the press point
  double retract_feed_mm_min = 0.0;                    // 0: rapid (G0) retract
  bool machine_coordinates = true;

  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

struct PressGcode {
  std::string approach;  // "G90 G53 G0 X.. Y.. Z.."
  std::string press;     // "G53 G1 X.. Y.. Z.. F.."
  std::string dwell;     // "G4 P0.300": its ok is the sync point
  std::string retract;   // "G53 G0 X.. Y.. Z.." back to the approach point; send after the frame
};

PressGcode MakePressGcode(const PressMotion& motion);

}  // namespace gs360
