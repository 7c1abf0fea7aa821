/*
 * ftsensord.h: a header-only C client for ftsensord's sample streams (C11 and C++17).
 *
 * One include, libzmq as the only library. A haptic loop opens one stream and, every
 * tick, takes the newest sample without blocking, and renders it only while it is live:
 *
 *     #include "ftsensord.h"
 *     fts_sub sub;                        // 1.6 KiB: one per stream, no global state
 *     fts_reading r;
 *     if (fts_open(&sub, "ipc:///run/ftsensord/wrench", "wrench/sensor1") != FTS_OK) ...
 *     for (;;) {                          // 1 kHz
 *         int rc = fts_latest(&sub, &r);  // never blocks, never hands out a backlog
 *         if (rc >= 0 && !(r.sample.flags & FTS_FLAG_INVALID))
 *             render(r.sample.values);    // fx fy fz (N) mx my mz (Nm), the stream's frame
 *         else
 *             render_nothing();           // rc < 0: no sample yet, or none for too long
 *     }
 *     fts_close(&sub);
 *
 * `rc >= 0` is the whole check: FTS_NEW is a new sample, FTS_SAME the previous one while
 * the stream is live. When nothing new has come for longer than FTS_STALE_PERIODS of the
 * stream's periods (timed on this host's clock alone, no shared clock needed) fts_latest
 * returns FTS_E_STALE instead: a killed or stopped (SIGSTOP) daemon never leaves the
 * loop rendering a frozen wrench. r still holds the last sample, with r.silent_s; a
 * restarted daemon's samples come back by themselves (FTS_NEW, r.restarted set).
 * fts_set_stale_after sets another limit in seconds.
 *
 * Each sample's sigma: a wrench stream's samples each have a companion on the stream
 * "sigma/" + its topic (kind 3, the same seq), the daemon's 1-sigma per axis of that wrench.
 * For a topic beginning "wrench/" fts_open subscribes a second conflating socket to it and
 * fts_latest gives r.sigma[6] (N, N, N, Nm, Nm, Nm) beside r.sample: the companion of the
 * very sample in r (matched by seq), NaN where the daemon says the sigma is unknown or
 * none of that seq came (a daemon that does not send it, or one not yet arrived: the two
 * streams travel on two connections, so a later call may fill it in). Define
 * FTS_NO_SIGMA before the include for one socket and r.sigma always NaN.
 *
 * The wire format is docs/reference/protocol.md's (ftsensord/protocol/wire.py writes it): one ZeroMQ
 * frame per sample, `topic NUL header(40 bytes) count*float64`, little-endian.
 *
 * How "the newest sample" is had: the publisher sends each sample as ONE frame whose
 * first bytes are the topic and a NUL, so a SUB socket per stream subscribes to
 * "topic\0" (exactly that stream: "wrench/sensor1" does not match "wrench/sensor10")
 * and sets ZMQ_CONFLATE before connecting, which keeps only the newest message in its
 * queue. CONFLATE would be wrong with multipart messages (it keeps one frame, not one
 * message) and conflates across everything a socket receives (so one socket per
 * stream, never one socket for several topics); neither applies here. fts_latest still
 * reads until the queue is empty (at most FTS_DRAIN_MAX frames), so even a socket
 * without conflation never hands out a backlog.
 *
 * Missed cycles: the daemon numbers each stream's samples by its cycle counter, so a
 * cycle the daemon skipped (its loop overran) is a jump in the sequence number.
 * fts_reading.missed is the number of sequence numbers this client never saw between
 * the sample the previous fts_latest call returned and this one: cycles the daemon
 * skipped, plus samples conflated away because the client read less often than the
 * stream publishes (never in a 1 kHz loop reading a 100 Hz stream), plus samples the
 * publisher dropped for a full queue. A sequence number that goes back means the daemon
 * restarted: `restarted` is set and nothing is counted as missed.
 *
 * Age: the daemon stamps t_mono with CLOCK_MONOTONIC (Python's time.monotonic() on
 * Linux) when the cycle's data were in hand; age_s = now - t_mono on this host's
 * CLOCK_MONOTONIC. That is meaningful only on the daemon's host (ipc, or tcp over
 * loopback); across hosts compare t_wall (CLOCK_REALTIME) with synchronised clocks.
 * silent_s, the time since this client first had the sample, is on this host's clock
 * alone, never compared with the daemon's: FTS_E_STALE is decided on it.
 *
 * Errors are negative return codes (fts_strerror names them); the header never aborts,
 * exits, prints or allocates. libzmq errors leave their errno in fts_sub.zmq_err.
 *
 * Alignment: in a received frame the header starts after the topic and its NUL, so its
 * fields and the values are at arbitrary offsets (the values of "wrench/sensor1" start
 * at byte 55). The decoder reads every field byte by byte and memcpy's the bits into a
 * double: no misaligned access, and correct on a big-endian host too.
 *
 * libzmq: if <zmq.h> is found (__has_include) it is included and the constants used are
 * checked against it at compile time. Otherwise (e.g. linking against the libzmq that the
 * pyzmq wheel ships without its header), or with FTSENSORD_NO_ZMQ_H defined, the header
 * declares the ten libzmq functions it calls itself: libzmq's C ABI is stable (zmq.h:
 * "the value of constants must not change"), and the declarations are identical to
 * zmq.h's, so both may appear in one translation unit. Needs libzmq >= 4.0 (CONFLATE).
 *
 * C needs POSIX's clock_gettime: compile with -D_POSIX_C_SOURCE=200809L (or -std=gnu11,
 * gcc's default); C++ compilers on glibc define it already.
 */
#ifndef FTSENSORD_H
#define FTSENSORD_H

#include <errno.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>
#include <time.h>

#if !defined(CLOCK_MONOTONIC)
#error "ftsensord.h needs POSIX clock_gettime(CLOCK_MONOTONIC): compile with -D_POSIX_C_SOURCE=200809L (or -std=gnu11)"
#endif

#if !defined(FTSENSORD_NO_ZMQ_H) && !defined(ZMQ_VERSION_MAJOR) && defined(__has_include)
#if __has_include(<zmq.h>)
#include <zmq.h>
#endif
#endif

#ifdef __cplusplus
#define FTS_STATIC_ASSERT_(cond, msg) static_assert(cond, msg)
extern "C" {
#else
#define FTS_STATIC_ASSERT_(cond, msg) _Static_assert(cond, msg)
#endif

/* The libzmq calls this header makes, declared exactly as zmq.h declares them. */
#if !defined(ZMQ_VERSION_MAJOR) || defined(FTSENSORD_DECLARE_ZMQ)
void *zmq_ctx_new(void);
int zmq_ctx_term(void *context);
void *zmq_socket(void *, int type);
int zmq_close(void *s);
int zmq_setsockopt(void *s, int option, const void *optval, size_t optvallen);
int zmq_connect(void *s, const char *addr);
int zmq_recv(void *s, void *buf, size_t len, int flags);
int zmq_send(void *s, const void *buf, size_t len, int flags);
int zmq_errno(void);
const char *zmq_strerror(int errnum);
#endif

/* libzmq's constants this header uses (stable ABI values). */
enum {
    FTS_ZMQ_PUB_ = 1,
    FTS_ZMQ_SUB_ = 2,
    FTS_ZMQ_SUBSCRIBE_ = 6,
    FTS_ZMQ_LINGER_ = 17,
    FTS_ZMQ_RCVTIMEO_ = 27,
    FTS_ZMQ_IPV6_ = 42,
    FTS_ZMQ_CONFLATE_ = 54,
    FTS_ZMQ_DONTWAIT_ = 1
};
#ifdef ZMQ_VERSION_MAJOR
FTS_STATIC_ASSERT_(ZMQ_PUB == FTS_ZMQ_PUB_ && ZMQ_SUB == FTS_ZMQ_SUB_ && ZMQ_SUBSCRIBE == FTS_ZMQ_SUBSCRIBE_ &&
                       ZMQ_LINGER == FTS_ZMQ_LINGER_ && ZMQ_RCVTIMEO == FTS_ZMQ_RCVTIMEO_ &&
                       ZMQ_CONFLATE == FTS_ZMQ_CONFLATE_ && ZMQ_DONTWAIT == FTS_ZMQ_DONTWAIT_ &&
                       ZMQ_IPV6 == FTS_ZMQ_IPV6_,
                   "ftsensord.h: libzmq constants differ from zmq.h");
#endif

/* An IPv6 address (tcp://[::1]:PORT) is reached only with ZMQ_IPV6 set; 0 or libzmq's -1. */
static inline int fts_ipv6_(void *sock, const char *endpoint)
{
    int one = 1;
    return strncmp(endpoint, "tcp://[", 7) == 0 ? zmq_setsockopt(sock, FTS_ZMQ_IPV6_, &one, sizeof one) : 0;
}

/* ---- the wire format (docs/reference/protocol.md; ftsensord/protocol/wire.py) -------------------- */
#define FTS_MAGIC 0x5446u /* the bytes 46 54, "FT", read as a little-endian u16 */
#define FTS_VERSION 1u
#define FTS_KIND_WRENCH 1u
#define FTS_KIND_FLUX 2u
#define FTS_KIND_SIGMA 3u      /* a wrench's 1-sigma per axis, on "sigma/" + the wrench's topic */
#define FTS_SIGMA_PREFIX "sigma/"
#define FTS_SIGMA_COUNT 6      /* values of a sigma sample: fx fy fz (N), mx my mz (Nm) */
#define FTS_HEADER_SIZE 40u

/* Status flags, as wire.py's FLAG_*: each marks every sample a condition affects. */
#define FTS_FLAG_CHIP_MISSING (1u << 0)  /* a chip did not answer this cycle */
#define FTS_FLAG_SATURATED (1u << 1)     /* a chip's reading was at or past its range */
#define FTS_FLAG_STALE (1u << 2)         /* a chip had no new data: its previous reading was used */
#define FTS_FLAG_OVERLOAD (1u << 3)      /* the wrench is beyond the sensor's range */
#define FTS_FLAG_DEGRADED (1u << 4)      /* estimated from fewer chips than calibrated */
#define FTS_FLAG_LATE (1u << 5)          /* the cycle began after its deadline */
#define FTS_FLAG_INVALID (1u << 6)       /* no estimate possible: the values are NaN */
#define FTS_FLAG_FALLBACK (1u << 7)      /* nonlinear estimator did not converge: linear used */
#define FTS_FLAG_EXTRAPOLATED (1u << 8)  /* a linear estimate beyond the calibration's loads */
#define FTS_FLAG_INCONSISTENT (1u << 9)  /* the chips disagree with each other: one reads wrong */
#define FTS_FLAG_ORIENTATION_STALE (1u << 10) /* compensated: orientation older than stale_after_s, or unknown */
#define FTS_FLAG_TEMPERATURE (1u << 11) /* a chip's temperature is beyond the span the compensation covers */

/* Sizes; define before including to change. A wrench has 6 values, flux 3 per chip. */
#ifndef FTS_MAX_VALUES
#define FTS_MAX_VALUES 48 /* flux of 16 chips */
#endif
#ifndef FTS_MAX_TOPIC
#define FTS_MAX_TOPIC 127 /* bytes of a topic, without its NUL */
#endif
#ifndef FTS_DRAIN_MAX
#define FTS_DRAIN_MAX 64 /* frames one fts_latest call reads at most (1 with CONFLATE) */
#endif
#ifndef FTS_SIGMA_KEEP
#define FTS_SIGMA_KEEP 4 /* companions kept to match their wrench: one may come before or after it */
#endif
#define FTS_FRAME_MAX (FTS_MAX_TOPIC + 1 + FTS_HEADER_SIZE + 8 * FTS_MAX_VALUES)

/* Staleness (fts_latest's FTS_E_STALE, fts_set_stale_after): the default limit on the time
 * without a new sample is FTS_STALE_PERIODS of the stream's period, at least FTS_STALE_MIN_S. */
#ifndef FTS_STALE_PERIODS
#define FTS_STALE_PERIODS 5.0 /* 4 cycles lost in a row: beyond a late or skipped cycle; 50 ms at 100 Hz */
#endif
#ifndef FTS_STALE_MIN_S
#define FTS_STALE_MIN_S 0.01 /* 10 ticks of a 1 kHz loop: a fast stream's hiccup is not a dead daemon */
#endif
#ifndef FTS_STALE_FIRST_S
#define FTS_STALE_FIRST_S 1.0 /* until two samples give the period: the default 100 Hz has it in 10 ms */
#endif
#ifndef FTS_PERIOD_SPAN
#define FTS_PERIOD_SPAN 16u /* sequence numbers the period is averaged over: a late stamp's error / 16 */
#endif
#define FTS_STALE_NEVER (-1.0) /* fts_set_stale_after: FTS_SAME for ever, no FTS_E_STALE */

/* Return codes: >= 0 success, < 0 an error. */
enum {
    FTS_OK = 0,
    FTS_SAME = 0,         /* fts_latest: no new sample since the previous call */
    FTS_NEW = 1,          /* fts_latest, fts_wait: a sample not returned before */
    FTS_E_NODATA = -1,    /* no sample has arrived yet */
    FTS_E_ZMQ = -2,       /* a libzmq call failed: fts_sub.zmq_err holds its errno */
    FTS_E_ARG = -3,       /* a NULL pointer, an empty topic or one over FTS_MAX_TOPIC */
    FTS_E_NOTOPIC = -4,   /* the frame has no NUL ending a topic */
    FTS_E_TOPIC = -5,     /* the frame's topic is not the one subscribed to */
    FTS_E_SHORT = -6,     /* the frame ends inside the 40-byte header */
    FTS_E_MAGIC = -7,     /* not an ftsensord sample */
    FTS_E_VERSION = -8,   /* a wire format version this header does not know */
    FTS_E_KIND = -9,      /* a kind other than wrench (1), flux (2) or sigma (3) */
    FTS_E_COUNT = -10,    /* more values than FTS_MAX_VALUES */
    FTS_E_LENGTH = -11,   /* the frame's length is not header + 8 * count */
    FTS_E_TOOBIG = -12,   /* the frame is longer than FTS_FRAME_MAX */
    FTS_E_CLOCK = -13,    /* clock_gettime(CLOCK_MONOTONIC) failed */
    FTS_E_TIMEOUT = -14,  /* fts_wait: nothing arrived in time */
    FTS_E_STALE = -15     /* fts_latest: nothing new for longer than the stale limit; r is filled */
};

/* One decoded sample. */
typedef struct fts_sample {
    uint64_t seq;                 /* the daemon's cycle number for this stream */
    double t_mono;                /* s, the daemon host's CLOCK_MONOTONIC when the data were in hand */
    double t_wall;                /* s, CLOCK_REALTIME (Unix time) at the same moment */
    uint32_t flags;               /* FTS_FLAG_* */
    uint16_t count;               /* values used: 6 for a wrench, 3 per chip for flux */
    uint8_t kind;                 /* FTS_KIND_WRENCH, FTS_KIND_FLUX or FTS_KIND_SIGMA */
    double values[FTS_MAX_VALUES]; /* wrench: fx fy fz (N), mx my mz (Nm); flux: T; sigma: N, Nm */
} fts_sample;

/* What fts_latest reports each tick. */
typedef struct fts_reading {
    fts_sample sample; /* the newest valid sample received so far */
    double age_s;      /* s, now - sample.t_mono (CLOCK_MONOTONIC; same host only) */
    double silent_s;   /* s since this client first had the sample (its own clock only) */
    uint64_t missed;   /* sequence numbers never seen since the previous call's sample */
    int fresh;         /* 1: sample is new since the previous call; 0: the same as then */
    int restarted;     /* 1: the sequence went back (daemon restarted); not counted missed */
    double sigma[FTS_SIGMA_COUNT]; /* 1-sigma per axis of sample.values (N, Nm), its companion's;
                                    * NaN: unknown, or not (yet) received; all NaN but a wrench's */
} fts_reading;

/* Counts missed cycles from sequence numbers. */
typedef struct fts_seq_track {
    uint64_t last;      /* the last sequence number seen */
    int have;           /* 0 until the first sample */
    uint64_t missed;    /* total sequence numbers skipped */
    uint64_t restarts;  /* times the sequence went back */
} fts_seq_track;

/* One subscription: one stream, one SUB socket. Fields are read-only for the caller. */
typedef struct fts_sub {
    void *ctx;
    void *sock;
    int own_ctx;
    int zmq_err;                      /* errno of the last failed libzmq call */
    size_t topic_len;
    char topic[FTS_MAX_TOPIC + 1];    /* the topic and its NUL: the subscription */
    fts_sample last;
    int have;
    fts_seq_track track;
    uint64_t pend_missed;             /* accumulated since the previous report */
    int pend_fresh, pend_restarted;
    uint64_t received, rejected;      /* frames received; of them refused by the decoder */
    int last_error;                   /* the decoder's last refusal (FTS_E_*), or 0 */
    double t_got;                     /* this host's CLOCK_MONOTONIC when `last` was first reported */
    double period_s;                  /* the stream's period from its stamps (fts_ingest_), 0: unknown */
    uint64_t span_seq;                /* the sample the period is measured from: its seq ... */
    double span_t;                    /* ... and its t_mono */
    double stale_after_s;             /* 0: FTS_STALE_PERIODS periods; > 0: seconds; < 0: never */
    void *sigma_sock;                 /* the companion "sigma/<topic>" of a wrench stream, or NULL */
    size_t sigma_topic_len;
    char sigma_topic[FTS_MAX_TOPIC + 7]; /* "sigma/" + topic and its NUL: the companion's subscription */
    struct {
        uint64_t seq;
        double values[FTS_SIGMA_COUNT];
    } sigmas[FTS_SIGMA_KEEP];         /* the newest companions received, matched to `last` by seq */
    unsigned sigma_count, sigma_next; /* slots filled; the slot the next one goes to */
    uint64_t sigma_rejected;          /* companion frames refused (the wrench is unaffected) */
    unsigned char frame[FTS_FRAME_MAX];
} fts_sub;

/* ---- decoding (no libzmq needed) ----------------------------------------------------------- */
static inline uint64_t fts_le_(const unsigned char *p, int n)
{
    uint64_t v = 0;
    for (int i = n - 1; i >= 0; --i) v = (v << 8) | p[i];
    return v;
}

static inline double fts_f64_(const unsigned char *p)
{
    uint64_t bits = fts_le_(p, 8);
    double d;
    memcpy(&d, &bits, sizeof d); /* IEEE 754 binary64 on both ends */
    return d;
}

/* Decode one frame of `len` bytes into *out. `topic` (topic_len bytes, no NUL needed)
 * is the topic the frame must carry, or NULL for any. Everything is checked before *out
 * is written: on an error *out is untouched. Returns FTS_OK or FTS_E_*. */
static inline int fts_decode(const void *frame, size_t len, const char *topic, size_t topic_len,
                             fts_sample *out)
{
    if (frame == NULL || out == NULL) return FTS_E_ARG;
    const unsigned char *f = (const unsigned char *)frame;
    const unsigned char *nul = (const unsigned char *)memchr(f, 0, len);
    if (nul == NULL) return FTS_E_NOTOPIC;
    size_t tlen = (size_t)(nul - f);
    if (topic != NULL && (tlen != topic_len || memcmp(f, topic, tlen) != 0)) return FTS_E_TOPIC;
    const unsigned char *h = nul + 1;
    size_t body = len - tlen - 1;
    if (body < FTS_HEADER_SIZE) return FTS_E_SHORT;
    if (fts_le_(h, 2) != FTS_MAGIC) return FTS_E_MAGIC;
    if (h[2] != FTS_VERSION) return FTS_E_VERSION;
    if (h[3] != FTS_KIND_WRENCH && h[3] != FTS_KIND_FLUX && h[3] != FTS_KIND_SIGMA) return FTS_E_KIND;
    size_t count = (size_t)fts_le_(h + 32, 2);
    if (count > FTS_MAX_VALUES) return FTS_E_COUNT;
    if (body != FTS_HEADER_SIZE + 8 * count) return FTS_E_LENGTH;
    out->kind = h[3];
    out->flags = (uint32_t)fts_le_(h + 4, 4);
    out->seq = fts_le_(h + 8, 8);
    out->t_mono = fts_f64_(h + 16);
    out->t_wall = fts_f64_(h + 24);
    out->count = (uint16_t)count;
    for (size_t i = 0; i < count; ++i) out->values[i] = fts_f64_(h + FTS_HEADER_SIZE + 8 * i);
    return FTS_OK;
}

/* Feed a sequence number; returns how many were skipped since the previous one (0 for
 * the first, a repeat, or a restart, which sets *restarted). */
static inline uint64_t fts_track(fts_seq_track *t, uint64_t seq, int *restarted)
{
    uint64_t skipped = 0;
    if (t->have && seq < t->last) { /* the daemon restarted: its numbering began anew */
        t->restarts++;
        if (restarted) *restarted = 1;
    } else if (t->have && seq > t->last) {
        skipped = seq - t->last - 1;
    }
    t->missed += skipped;
    t->last = seq;
    t->have = 1;
    return skipped;
}

/* Seconds on CLOCK_MONOTONIC, or a negative value if the clock failed. */
static inline double fts_now(void)
{
    struct timespec ts;
    if (clock_gettime(CLOCK_MONOTONIC, &ts) != 0) return -1.0;
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

static inline const char *fts_strerror(int rc)
{
    switch (rc) {
    case FTS_OK: return "ok";
    case FTS_NEW: return "new sample";
    case FTS_E_NODATA: return "no sample has arrived yet";
    case FTS_E_ZMQ: return "a libzmq call failed (see zmq_err)";
    case FTS_E_ARG: return "bad argument (NULL, or an empty or too long topic)";
    case FTS_E_NOTOPIC: return "frame without a NUL-terminated topic";
    case FTS_E_TOPIC: return "frame of another topic";
    case FTS_E_SHORT: return "frame shorter than its 40-byte header";
    case FTS_E_MAGIC: return "not an ftsensord sample (bad magic)";
    case FTS_E_VERSION: return "unknown wire format version";
    case FTS_E_KIND: return "unknown sample kind";
    case FTS_E_COUNT: return "more values than FTS_MAX_VALUES";
    case FTS_E_LENGTH: return "frame length does not match its value count";
    case FTS_E_TOOBIG: return "frame longer than FTS_FRAME_MAX";
    case FTS_E_CLOCK: return "clock_gettime(CLOCK_MONOTONIC) failed";
    case FTS_E_TIMEOUT: return "no sample within the timeout";
    case FTS_E_STALE: return "nothing new for longer than the stale limit (is the daemon running?)";
    default: return "unknown ftsensord.h error";
    }
}

/* The wire.py name of one flag bit ("chip_missing", ...), or NULL. */
static inline const char *fts_flag_name(uint32_t bit)
{
    switch (bit) {
    case FTS_FLAG_CHIP_MISSING: return "chip_missing";
    case FTS_FLAG_SATURATED: return "saturated";
    case FTS_FLAG_STALE: return "stale";
    case FTS_FLAG_OVERLOAD: return "overload";
    case FTS_FLAG_DEGRADED: return "degraded";
    case FTS_FLAG_LATE: return "late";
    case FTS_FLAG_INVALID: return "invalid";
    case FTS_FLAG_FALLBACK: return "fallback";
    case FTS_FLAG_EXTRAPOLATED: return "extrapolated";
    case FTS_FLAG_INCONSISTENT: return "inconsistent";
    case FTS_FLAG_ORIENTATION_STALE: return "orientation_stale";
    case FTS_FLAG_TEMPERATURE: return "temperature";
    default: return NULL;
    }
}

/* ---- subscribing --------------------------------------------------------------------------- */
static inline int fts_zfail_(fts_sub *s)
{
    s->zmq_err = zmq_errno();
    return FTS_E_ZMQ;
}

static inline void fts_close(fts_sub *s)
{
    if (s == NULL) return;
    if (s->sock != NULL) zmq_close(s->sock);
    if (s->sigma_sock != NULL) zmq_close(s->sigma_sock);
    if (s->own_ctx && s->ctx != NULL) zmq_ctx_term(s->ctx);
    s->sock = NULL;
    s->sigma_sock = NULL;
    s->ctx = NULL;
    s->own_ctx = 0;
}

/* A SUB socket on `ctx` subscribed to exactly `topic\0` (n bytes and the NUL), conflating,
 * connected to `endpoint`; NULL with s->zmq_err set on a failure. */
static inline void *fts_sub_socket_(fts_sub *s, void *ctx, const char *endpoint, const char *topic, size_t n)
{
    void *sock = zmq_socket(ctx, FTS_ZMQ_SUB_);
    if (sock == NULL) {
        fts_zfail_(s);
        return NULL;
    }
    int one = 1, zero = 0;
    /* CONFLATE acts on connections made after it is set: before zmq_connect. */
    if (zmq_setsockopt(sock, FTS_ZMQ_CONFLATE_, &one, sizeof one) != 0 ||
        zmq_setsockopt(sock, FTS_ZMQ_LINGER_, &zero, sizeof zero) != 0 ||
        zmq_setsockopt(sock, FTS_ZMQ_SUBSCRIBE_, topic, n + 1) != 0 || fts_ipv6_(sock, endpoint) != 0 ||
        zmq_connect(sock, endpoint) != 0) {
        fts_zfail_(s);
        zmq_close(sock);
        return NULL;
    }
    return sock;
}

/* Subscribe to one stream (e.g. "wrench/sensor1") of the daemon at `endpoint`
 * ("ipc:///run/ftsensord/wrench", "tcp://127.0.0.1:5555") on a libzmq context the caller
 * owns and keeps until fts_close. Connecting does not wait for the daemon: samples
 * arrive once it runs, and after a daemon restart. A "wrench/..." stream's sigma comes
 * on a second socket subscribed to its companion "sigma/wrench/..." (unless FTS_NO_SIGMA). */
static inline int fts_open_ctx(fts_sub *s, void *ctx, const char *endpoint, const char *topic)
{
    if (s == NULL || ctx == NULL || endpoint == NULL || topic == NULL) return FTS_E_ARG;
    memset(s, 0, sizeof *s);
    size_t n = strlen(topic);
    if (n == 0 || n > FTS_MAX_TOPIC) return FTS_E_ARG;
    memcpy(s->topic, topic, n); /* the memset left the NUL that ends the subscription */
    s->topic_len = n;
    s->ctx = ctx;
    s->sock = fts_sub_socket_(s, ctx, endpoint, s->topic, n);
    if (s->sock == NULL) return FTS_E_ZMQ;
#ifndef FTS_NO_SIGMA
    if (strncmp(topic, "wrench/", 7) == 0) {
        size_t p = sizeof FTS_SIGMA_PREFIX - 1;
        memcpy(s->sigma_topic, FTS_SIGMA_PREFIX, p);
        memcpy(s->sigma_topic + p, topic, n); /* the memset left its NUL too */
        s->sigma_topic_len = p + n;
        s->sigma_sock = fts_sub_socket_(s, ctx, endpoint, s->sigma_topic, s->sigma_topic_len);
        if (s->sigma_sock == NULL) {
            zmq_close(s->sock);
            s->sock = NULL;
            return FTS_E_ZMQ;
        }
    }
#endif
    return FTS_OK;
}

/* As fts_open_ctx, with a context of the subscription's own (one I/O thread). */
static inline int fts_open(fts_sub *s, const char *endpoint, const char *topic)
{
    if (s == NULL) return FTS_E_ARG;
    void *ctx = zmq_ctx_new();
    if (ctx == NULL) {
        memset(s, 0, sizeof *s);
        return fts_zfail_(s);
    }
    int rc = fts_open_ctx(s, ctx, endpoint, topic);
    if (rc != FTS_OK) {
        zmq_ctx_term(ctx);
        s->ctx = NULL;
        return rc;
    }
    s->own_ctx = 1;
    return FTS_OK;
}

/* Decode the n-byte frame just received into s->last and account for its sequence. */
static inline int fts_ingest_(fts_sub *s, int n)
{
    s->received++;
    int rc = (size_t)n > sizeof s->frame
                 ? FTS_E_TOOBIG
                 : fts_decode(s->frame, (size_t)n, s->topic, s->topic_len, &s->last);
    if (rc != FTS_OK) {
        s->rejected++;
        s->last_error = rc;
        return rc;
    }
    s->pend_missed += fts_track(&s->track, s->last.seq, &s->pend_restarted);
    /* The period from the daemon's stamps, not arrival times: its clock's differences hold
     * on this host or another, and a skipped cycle is a sequence jump the division takes out. The first
     * two samples give it; then each FTS_PERIOD_SPAN sequence numbers. A first sample or a
     * restart (the sequence going back) begins a new span, the period kept. */
    uint64_t span = s->have && s->last.seq > s->span_seq ? s->last.seq - s->span_seq : 0;
    if (span > 0 && (s->period_s <= 0.0 || span >= FTS_PERIOD_SPAN) && s->last.t_mono > s->span_t)
        s->period_s = (s->last.t_mono - s->span_t) / (double)span;
    if (span == 0 || span >= FTS_PERIOD_SPAN) {
        s->span_seq = s->last.seq;
        s->span_t = s->last.t_mono;
    }
    s->have = 1;
    s->pend_fresh = 1;
    return FTS_OK;
}

/* Set how long fts_latest goes on returning FTS_SAME without a new sample before it
 * returns FTS_E_STALE: `seconds` > 0, that long; 0, the default, FTS_STALE_PERIODS of the
 * stream's period (at least FTS_STALE_MIN_S; FTS_STALE_FIRST_S until two samples gave the
 * period); FTS_STALE_NEVER (any negative), never. FTS_E_ARG for a NULL or a NaN. */
static inline int fts_set_stale_after(fts_sub *s, double seconds)
{
    if (s == NULL || seconds != seconds) return FTS_E_ARG;
    s->stale_after_s = seconds;
    return FTS_OK;
}

/* The limit now in force (s), as fts_set_stale_after says; negative: never stale. */
static inline double fts_stale_limit(const fts_sub *s)
{
    if (s->stale_after_s != 0.0) return s->stale_after_s < 0.0 ? FTS_STALE_NEVER : s->stale_after_s;
    if (s->period_s <= 0.0) return FTS_STALE_FIRST_S;
    double limit = FTS_STALE_PERIODS * s->period_s;
    return limit > FTS_STALE_MIN_S ? limit : FTS_STALE_MIN_S;
}

/* A double with every bit of a quiet NaN: "unknown", without <math.h>. */
static inline double fts_nan_(void)
{
    uint64_t bits = 0x7FF8000000000000ull;
    double d;
    memcpy(&d, &bits, sizeof d);
    return d;
}

/* Read every companion waiting (one, with CONFLATE) into s->sigmas; never blocks, never
 * fails the wrench: a refused frame or a libzmq error is counted in s->sigma_rejected. */
static inline void fts_sigma_drain_(fts_sub *s)
{
    if (s->sigma_sock == NULL) return;
    fts_sample c;
    for (int i = 0; i < FTS_DRAIN_MAX; ++i) {
        int n = zmq_recv(s->sigma_sock, s->frame, sizeof s->frame, FTS_ZMQ_DONTWAIT_);
        if (n < 0) {
            int e = zmq_errno();
            if (e != EAGAIN && e != EINTR) s->sigma_rejected++;
            return;
        }
        if ((size_t)n > sizeof s->frame ||
            fts_decode(s->frame, (size_t)n, s->sigma_topic, s->sigma_topic_len, &c) != FTS_OK ||
            c.kind != FTS_KIND_SIGMA || c.count != FTS_SIGMA_COUNT) {
            s->sigma_rejected++;
            continue;
        }
        s->sigmas[s->sigma_next].seq = c.seq;
        memcpy(s->sigmas[s->sigma_next].values, c.values, sizeof s->sigmas[0].values);
        s->sigma_next = (s->sigma_next + 1) % FTS_SIGMA_KEEP;
        if (s->sigma_count < FTS_SIGMA_KEEP) s->sigma_count++;
    }
}

/* out[6]: the companion of sequence number `seq` if one was received and is still kept, else NaN. */
static inline void fts_sigma_of_(const fts_sub *s, uint64_t seq, double *out)
{
    for (unsigned i = 0; i < s->sigma_count; ++i) {
        if (s->sigmas[i].seq == seq) {
            memcpy(out, s->sigmas[i].values, sizeof s->sigmas[i].values);
            return;
        }
    }
    for (int k = 0; k < FTS_SIGMA_COUNT; ++k) out[k] = fts_nan_();
}

/* The newest sample, without blocking. Reads every frame waiting (one, with CONFLATE),
 * keeps the newest valid one, and fills *r with it, its age and the cycles missed since
 * the previous call, and r->sigma with its companion's sigma (NaN: unknown or not received).
 * Returns FTS_NEW (a sample not returned before), FTS_SAME (none
 * since the previous call: r->sample is the previous one, its age grown), FTS_E_STALE
 * (none for longer than fts_stale_limit: *r filled as for FTS_SAME, r->silent_s past the
 * limit; the same until a new sample comes), or an error with *r untouched:
 * FTS_E_NODATA (nothing yet), FTS_E_ZMQ, FTS_E_CLOCK, or the decoder's refusal of the
 * newest frame (counted in s->rejected; it is gone, and the next call reports the last
 * valid sample again). */
static inline int fts_latest(fts_sub *s, fts_reading *r)
{
    if (s == NULL || r == NULL || s->sock == NULL) return FTS_E_ARG;
    /* Companions before and after the wrenches: each is sent just before its wrench but on
     * a connection of its own, so it may be in either read; FTS_SIGMA_KEEP holds both. */
    fts_sigma_drain_(s);
    int newest = FTS_OK;
    for (int i = 0; i < FTS_DRAIN_MAX; ++i) {
        int n = zmq_recv(s->sock, s->frame, sizeof s->frame, FTS_ZMQ_DONTWAIT_);
        if (n < 0) {
            int e = zmq_errno();
            if (e == EAGAIN || e == EINTR) break; /* queue empty, or a signal: next tick */
            s->zmq_err = e;
            return FTS_E_ZMQ;
        }
        newest = fts_ingest_(s, n);
    }
    fts_sigma_drain_(s);
    if (newest != FTS_OK) return newest;
    if (!s->have) return FTS_E_NODATA;
    double now = fts_now();
    if (now < 0) return FTS_E_CLOCK;
    if (s->pend_fresh) s->t_got = now; /* within a tick of its arrival: each tick drains the queue */
    memcpy(&r->sample, &s->last, offsetof(fts_sample, values) + sizeof(double) * s->last.count);
    r->age_s = now - s->last.t_mono;
    r->silent_s = now - s->t_got;
    r->missed = s->pend_missed;
    r->fresh = s->pend_fresh;
    r->restarted = s->pend_restarted;
    fts_sigma_of_(s, s->last.seq, r->sigma); /* a companion late on its connection fills in later */
    s->pend_missed = 0;
    s->pend_fresh = s->pend_restarted = 0;
    if (r->fresh) return FTS_NEW;
    double limit = fts_stale_limit(s);
    /* Every call since t_got found the queue empty: the stream was silent at least silent_s. */
    return limit >= 0.0 && r->silent_s > limit ? FTS_E_STALE : FTS_SAME;
}

/* Block until a sample arrives (at most timeout_ms; -1: forever), then as fts_latest.
 * For start-up and tools, not for the haptic loop. Returns FTS_NEW, FTS_E_TIMEOUT, or
 * an error as fts_latest; a signal ends the wait with FTS_E_ZMQ and zmq_err EINTR. */
static inline int fts_wait(fts_sub *s, fts_reading *r, int timeout_ms)
{
    if (s == NULL || r == NULL || s->sock == NULL) return FTS_E_ARG;
    if (!s->pend_fresh) {
        if (zmq_setsockopt(s->sock, FTS_ZMQ_RCVTIMEO_, &timeout_ms, sizeof timeout_ms) != 0)
            return fts_zfail_(s);
        int n = zmq_recv(s->sock, s->frame, sizeof s->frame, 0);
        if (n < 0) {
            int e = zmq_errno();
            if (e == EAGAIN) return FTS_E_TIMEOUT;
            s->zmq_err = e;
            return FTS_E_ZMQ;
        }
        int rc = fts_ingest_(s, n);
        if (rc != FTS_OK) return rc;
    }
    return fts_latest(s, r);
}

/* ---- the orientation stream: gravity compensation (docs/guide/clients.md) ------------------------
 * The haptic application tells the daemon how the tool is turned: a unit quaternion
 * [w x y z] (Hamilton) of R_world,frame for a sensor's name or "tip", with its own time.
 * PUB, connected to the daemon's ipc://<runtime>/orientation: a send never blocks. */
#define FTS_ORIENT_SIZE 80u /* the quaternion message: 48-byte header, 4 doubles */

static inline void fts_put_f64le_(unsigned char *p, double v)
{
    uint64_t u;
    memcpy(&u, &v, sizeof u);
    for (int i = 0; i < 8; ++i) p[i] = (unsigned char)(u >> (8 * i));
}

/* Encode one orientation message into out (FTS_ORIENT_SIZE bytes); FTS_E_ARG for a NULL,
 * an empty frame name or one over 31 characters. */
static inline int fts_orientation_encode(unsigned char *out, const char *frame, const double q_wxyz[4],
                                         double t_sender)
{
    if (out == NULL || frame == NULL || q_wxyz == NULL) return FTS_E_ARG;
    size_t n = strlen(frame);
    if (n == 0 || n > 31) return FTS_E_ARG;
    memset(out, 0, FTS_ORIENT_SIZE);
    memcpy(out, "FTOR", 4);
    out[4] = 1; /* version */
    out[5] = 1; /* representation: quaternion */
    memcpy(out + 8, frame, n);
    fts_put_f64le_(out + 40, t_sender);
    for (int i = 0; i < 4; ++i) fts_put_f64le_(out + 48 + 8 * i, q_wxyz[i]);
    return FTS_OK;
}

typedef struct {
    void *ctx, *sock;
    int zmq_err; /* libzmq's errno of the last FTS_E_ZMQ */
} fts_orient;

static inline void fts_orientation_close(fts_orient *p)
{
    if (p == NULL) return;
    if (p->sock != NULL) zmq_close(p->sock);
    if (p->ctx != NULL) zmq_ctx_term(p->ctx);
    p->sock = p->ctx = NULL;
}

/* Connect a publisher of orientations to the daemon's endpoint (it need not run yet). */
static inline int fts_orientation_open(fts_orient *p, const char *endpoint)
{
    if (p == NULL || endpoint == NULL) return FTS_E_ARG;
    memset(p, 0, sizeof *p);
    int zero = 0;
    if ((p->ctx = zmq_ctx_new()) == NULL || (p->sock = zmq_socket(p->ctx, FTS_ZMQ_PUB_)) == NULL ||
        zmq_setsockopt(p->sock, FTS_ZMQ_LINGER_, &zero, sizeof zero) != 0 || fts_ipv6_(p->sock, endpoint) != 0 ||
        zmq_connect(p->sock, endpoint) != 0) {
        p->zmq_err = zmq_errno();
        fts_orientation_close(p);
        return FTS_E_ZMQ;
    }
    return FTS_OK;
}

/* Send R_world,frame as a unit quaternion; never blocks (a full queue drops it: the
 * daemon keeps the newest anyway). */
static inline int fts_orientation_send(fts_orient *p, const char *frame, const double q_wxyz[4], double t_sender)
{
    unsigned char m[FTS_ORIENT_SIZE];
    if (p == NULL || p->sock == NULL) return FTS_E_ARG;
    int rc = fts_orientation_encode(m, frame, q_wxyz, t_sender);
    if (rc != FTS_OK) return rc;
    if (zmq_send(p->sock, m, sizeof m, FTS_ZMQ_DONTWAIT_) < 0 && zmq_errno() != EAGAIN) {
        p->zmq_err = zmq_errno();
        return FTS_E_ZMQ;
    }
    return FTS_OK;
}

#ifdef __cplusplus
} /* extern "C" */
#endif

#endif /* FTSENSORD_H */
