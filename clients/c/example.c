/*
 * example.c: a 1 kHz loop that reads the newest wrench of one ftsensord stream each tick
 * and prints its age and force once a second. Ctrl-C (or SIGTERM) stops it.
 *
 *     example [-e ENDPOINT] [-t TOPIC] [-n TICKS] [-s SECONDS] [-w SECONDS] [--dump]
 *
 *   -e  the daemon's publisher (default: ipc:///run/ftsensord/wrench if that socket
 *       exists, else $XDG_RUNTIME_DIR/ftsensord/wrench, else /tmp/ftsensord-<uid>/wrench:
 *       where `ftsensord run` puts it)
 *   -t  the stream (default wrench/sensor1)
 *   -n  stop after this many ticks; -s after this many seconds (default: run until Ctrl-C)
 *   -w  give up after this many seconds without a first sample (default 5)
 *   --dump  also print every new sample: seq, flags, t_mono, missed, the six values and
 *           their sigma (NaN: unknown, or not received) with 17 significant digits (enough
 *           to give back the exact doubles)
 *
 * Exit status: 0 when samples came; 1 when none came, within the -w wait or before the run
 * ended (a message on stderr says where it listened); 2 for a bad argument. Samples that
 * stop coming later are reported (FTS_E_STALE), not rendered, and the loop goes on.
 *
 * Build (clients/c/build.py finds libzmq, the system's or, failing that, the pyzmq wheel's):
 *     python clients/c/build.py            # prints the compiler command it ran
 *     cc -std=c11 -O2 example.c -o example -lzmq   # with a system libzmq
 */
#define _POSIX_C_SOURCE 200809L

#include "ftsensord.h"

#include <inttypes.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#define PERIOD_NS 1000000L /* 1 kHz, a haptic servo rate */
#define NS_PER_S 1000000000L
#define FIRST_WAIT_S 5.0 /* the daemon's start-up takes seconds on a loaded 2-core host; a wrong endpoint never answers */

static volatile sig_atomic_t stop_requested = 0;

static void on_signal(int sig)
{
    (void)sig;
    stop_requested = 1;
}

static void default_endpoint(char *out, size_t size)
{
    const char *xdg = getenv("XDG_RUNTIME_DIR");
    if (access("/run/ftsensord/wrench", F_OK) == 0)
        snprintf(out, size, "ipc:///run/ftsensord/wrench");
    else if (xdg != NULL && xdg[0] != '\0')
        snprintf(out, size, "ipc://%s/ftsensord/wrench", xdg);
    else
        snprintf(out, size, "ipc:///tmp/ftsensord-%lu/wrench", (unsigned long)getuid());
}

static void add_ns(struct timespec *t, long ns)
{
    t->tv_nsec += ns;
    while (t->tv_nsec >= NS_PER_S) {
        t->tv_nsec -= NS_PER_S;
        t->tv_sec++;
    }
}

static int usage(const char *prog)
{
    fprintf(stderr, "usage: %s [-e ENDPOINT] [-t TOPIC] [-n TICKS] [-s SECONDS] [-w SECONDS] [--dump]\n", prog);
    return 2;
}

int main(int argc, char **argv)
{
    char endpoint[512];
    const char *topic = "wrench/sensor1";
    unsigned long long max_ticks = 0; /* 0: until a signal */
    double first_wait_s = FIRST_WAIT_S;
    int dump = 0;
    default_endpoint(endpoint, sizeof endpoint);
    for (int i = 1; i < argc; ++i) {
        int has_value = i + 1 < argc;
        if (strcmp(argv[i], "-e") == 0 && has_value) {
            snprintf(endpoint, sizeof endpoint, "%s", argv[++i]);
        } else if (strcmp(argv[i], "-t") == 0 && has_value) {
            topic = argv[++i];
        } else if (strcmp(argv[i], "-n") == 0 && has_value) {
            max_ticks = strtoull(argv[++i], NULL, 10);
        } else if (strcmp(argv[i], "-s") == 0 && has_value) {
            max_ticks = (unsigned long long)(strtod(argv[++i], NULL) * 1000.0 + 0.5);
        } else if (strcmp(argv[i], "-w") == 0 && has_value) {
            first_wait_s = strtod(argv[++i], NULL);
        } else if (strcmp(argv[i], "--dump") == 0) {
            dump = 1;
        } else {
            return usage(argv[0]);
        }
    }

    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigemptyset(&sa.sa_mask);
    sa.sa_flags = 0; /* no SA_RESTART: a signal ends the tick's sleep at once */
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGTERM, &sa, NULL);

    fts_sub sub;
    int rc = fts_open(&sub, endpoint, topic);
    if (rc != FTS_OK) {
        fprintf(stderr, "cannot subscribe to %s on %s: %s%s%s\n", topic, endpoint, fts_strerror(rc),
                rc == FTS_E_ZMQ ? ": " : "", rc == FTS_E_ZMQ ? zmq_strerror(sub.zmq_err) : "");
        return 1;
    }
    printf("reading %s from %s at 1 kHz\n", topic, endpoint);
    fflush(stdout);

    unsigned long long ticks = 0, fresh = 0, missed = 0, overruns = 0;
    const unsigned long long wait_ticks = (unsigned long long)(first_wait_s * 1000.0 + 0.5);
    int last_error = FTS_OK;
    fts_reading r;
    memset(&r, 0, sizeof r);
    struct timespec next;
    clock_gettime(CLOCK_MONOTONIC, &next);
    while (!stop_requested && (max_ticks == 0 || ticks < max_ticks) && (fresh > 0 || ticks < wait_ticks)) {
        rc = fts_latest(&sub, &r);
        if (rc == FTS_NEW) {
            fresh++;
            missed += r.missed;
            if (dump) {
                printf("sample seq=%" PRIu64 " flags=0x%" PRIx32 " t_mono=%.9f missed=%" PRIu64 " values=",
                       r.sample.seq, r.sample.flags, r.sample.t_mono, r.missed);
                for (int k = 0; k < r.sample.count; ++k) printf("%s%.17g", k ? "," : "", r.sample.values[k]);
                printf(" sigma=");
                for (int k = 0; k < FTS_SIGMA_COUNT; ++k) printf("%s%.17g", k ? "," : "", r.sigma[k]);
                printf("\n");
            }
        } else if (rc < 0 && rc != FTS_E_NODATA && rc != last_error) {
            fprintf(stderr, "tick %llu: %s\n", ticks, fts_strerror(rc)); /* once each time it begins */
        }
        last_error = rc;

        /* ... the haptic rendering would use r.sample.values here when rc >= 0, and render
         * no force otherwise: rc < 0 is no sample yet, or none for too long (FTS_E_STALE) ... */

        ticks++;
        if (ticks % 1000 == 0) {
            if (rc >= 0)
                printf("%llu s: age %.3f ms, f = [%+.4f %+.4f %+.4f] N, flags 0x%" PRIx32 ", missed %llu\n",
                       ticks / 1000, 1e3 * r.age_s, r.sample.values[0], r.sample.values[1],
                       r.sample.values[2], r.sample.flags, missed);
            else
                printf("%llu s: %s\n", ticks / 1000, fts_strerror(rc));
            fflush(stdout);
        }

        add_ns(&next, PERIOD_NS);
        struct timespec now;
        clock_gettime(CLOCK_MONOTONIC, &now);
        if ((now.tv_sec - next.tv_sec) * NS_PER_S + (now.tv_nsec - next.tv_nsec) > PERIOD_NS) {
            overruns++; /* more than a tick behind: start afresh rather than run a burst of ticks */
            next = now;
        }
        while (!stop_requested && clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL) == EINTR) {
        }
    }
    printf("ticks %llu, new samples %llu, missed cycles %llu, rejected frames %" PRIu64 ", overruns %llu\n",
           ticks, fresh, missed, sub.rejected, overruns);
    fts_close(&sub);
    if (fresh == 0) { /* a run with nothing to show must not pass for a working one in a script */
        fprintf(stderr, "no sample of %s from %s in %.1f s: is ftsensord running (ftsensord status), "
                "and is this its publisher (-e)?\n", topic, endpoint, (double)ticks / 1000.0);
        return 1;
    }
    return 0;
}
