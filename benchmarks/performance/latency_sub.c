/*
 * latency_sub.c: N subscribers of one stream in one C process, as haptic loops built on
 * clients/c/ftsensord.h would be. Built and run by benchmarks/performance/latency.py (--kind c).
 *
 *     latency_sub ENDPOINT TOPIC N SETTLE_S SECONDS [shared]
 *
 * Opens N subscriptions with fts_open (each its own libzmq context and I/O thread, as N
 * separate programs would have; with "shared", fts_open_ctx on one context: one I/O
 * thread for the N, as one program with N subscriptions would have), waits on all of them with zmq_poll, and takes every
 * sample as it arrives with fts_latest. After SETTLE_S seconds (connections made, the
 * first samples through), for SECONDS it records each receipt's delay: CLOCK_MONOTONIC at
 * receipt minus the sample's t_mono (the daemon's CLOCK_MONOTONIC when the chips had been
 * read). Prints one line per receipt, "seq delay_ns", then to stderr a summary line.
 */
#define _POSIX_C_SOURCE 200809L

#include "ftsensord.h"

#include <stdio.h>
#include <stdlib.h>

#ifdef FTSENSORD_NO_ZMQ_H
/* The pyzmq wheel ships libzmq without zmq.h: the one more function this program calls. */
typedef struct {
    void *socket;
    int fd;
    short events;
    short revents;
} zmq_pollitem_t;
int zmq_poll(zmq_pollitem_t *items, int nitems, long timeout);
#define ZMQ_POLLIN 1
#endif

int main(int argc, char **argv)
{
    if (argc != 6 && argc != 7) {
        fprintf(stderr, "usage: %s ENDPOINT TOPIC N SETTLE_S SECONDS [shared]\n", argv[0]);
        return 2;
    }
    int n = atoi(argv[3]);
    double settle = atof(argv[4]), seconds = atof(argv[5]);
    if (n < 1 || seconds <= 0) return 2;
    fts_sub *subs = (fts_sub *)calloc((size_t)n, sizeof *subs);
    zmq_pollitem_t *items = (zmq_pollitem_t *)calloc((size_t)n, sizeof *items);
    /* 200 samples a second per subscriber is twice the daemon's default rate. */
    size_t cap = (size_t)n * (size_t)((seconds + 1.0) * 200.0), count = 0;
    long long *delays = (long long *)malloc(cap * sizeof *delays);
    unsigned long long *seqs = (unsigned long long *)malloc(cap * sizeof *seqs);
    if (subs == NULL || items == NULL || delays == NULL || seqs == NULL) return 1;
    void *shared = argc == 7 ? zmq_ctx_new() : NULL;
    if (argc == 7 && shared == NULL) return 1;
    for (int i = 0; i < n; ++i) {
        int rc = shared ? fts_open_ctx(&subs[i], shared, argv[1], argv[2]) : fts_open(&subs[i], argv[1], argv[2]);
        if (rc != FTS_OK) {
            fprintf(stderr, "fts_open %s %s: %s\n", argv[1], argv[2], fts_strerror(rc));
            return 1;
        }
        items[i].socket = subs[i].sock;
        items[i].events = ZMQ_POLLIN;
    }
    double start = fts_now(), end = start + settle + seconds;
    unsigned long long errors = 0, missed = 0;
    fts_reading r;
    for (;;) {
        double now = fts_now();
        if (now >= end) break;
        /* 100 ms at most: the end is checked even when no sample comes. */
        if (zmq_poll(items, n, 100) < 0) {
            if (zmq_errno() == EINTR) continue;
            fprintf(stderr, "zmq_poll: %s\n", zmq_strerror(zmq_errno()));
            return 1;
        }
        for (int i = 0; i < n; ++i) {
            if (!(items[i].revents & ZMQ_POLLIN)) continue;
            int rc = fts_latest(&subs[i], &r); /* r.age_s: now - t_mono, taken at receipt */
            if (rc == FTS_NEW) {
                if (r.sample.t_mono - start >= settle && count < cap) {
                    seqs[count] = (unsigned long long)r.sample.seq;
                    delays[count++] = (long long)(r.age_s * 1e9);
                    missed += r.missed;
                }
            } else if (rc < 0) {
                errors++;
            }
        }
    }
    for (size_t i = 0; i < count; ++i) printf("%llu %lld\n", seqs[i], delays[i]);
    fprintf(stderr, "subscribers %d receipts %zu missed %llu errors %llu\n", n, count, missed, errors);
    for (int i = 0; i < n; ++i) fts_close(&subs[i]);
    if (shared) zmq_ctx_term(shared);
    free(delays);
    free(seqs);
    free(items);
    free(subs);
    return 0;
}
