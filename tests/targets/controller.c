/* A small EG-Link machine controller (TS-0006) in C, for the fuzzer's own tests.
 *
 *   controller LISTEN_PORT PEER_PORT      (UDP on 127.0.0.1 only)
 *
 * Correct unless built with one planted bug:
 *   -DBUG_HEAP_OVERFLOW  a VRPI with vlaps above 3 clears past a heap array (record_laps)
 *   -DBUG_NULL_CALL      a VRPI with an unknown bu_state calls through a NULL handler (dispatch_state)
 *   -DBUG_LAP_SLOT       a VRPI with vlaps above 3 writes through the NULL its lap slot lookup gave (record_laps)
 *   -DBUG_DEEP           VRCI "MAINT:" then VRCI "ENGAGE" writes through a NULL pointer (maintenance_engage):
 *                        two multi-byte comparisons and a state, out of reach of blind mutation
 *   -DBUG_ABORT          a VRCI with command ID 65535 fails an assertion-like abort() (on_vrci)
 *   -DBUG_LEAK           every legal VRCI leaks a 64 KiB buffer it wrote (on_vrci): no crash, the RSS grows
 *   -DBUG_LEAK_UNKNOWN   every packet with an unknown ID (and a right CRC) leaks 64 KiB (on_datagram): a
 *                        leak on a rare packet kind, one case in some 14
 * and with -DCHURN (no bug) every legal VRCI writes a 64 KiB buffer and frees it.
 *
 * VRPO every 100 ms, a VRCO every second (resent every 100 ms until its VRAI, given up after
 * 2 s), a VRAO for every legal VRCI; a command ID heard again within 2 s is a retransmission
 * (acknowledged, not executed). Illegal packets (size not the datagram's, revision, CRC, unknown ID,
 * short payload) are ignored.
 * CRC-32/MPEG-2 over ID, header and payload, stored little-endian after the payload.
 */
#include <arpa/inet.h>
#include <errno.h>
#include <poll.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#define PREFIX_LEN 16
#define OVERHEAD 20
#define MAX_PACKET 512
#define VRPI_SIZE 46
#define COMMAND_SIZE 22
#define ACK_SIZE 2
#define REUSE_GAP_MS 2000
#define IDS_KEPT 64

static int sock = -1;
static struct sockaddr_in peer;
static uint16_t out_serial;
static volatile sig_atomic_t stopping;

static struct {
    int bu_state;
    int ru_armed;
    int maintenance;
    long executed;
} state;

static struct {
    uint16_t id;
    int64_t at;
} heard[IDS_KEPT];
static int heard_next;

static struct {
    int in_flight;
    uint16_t id;
    int64_t first, last;
} vrco;
static uint16_t vrco_next_id;

static int64_t now_ms(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000 + ts.tv_nsec / 1000000;
}

static uint32_t crc32_mpeg2(const uint8_t *data, size_t len)
{
    uint32_t crc = 0xFFFFFFFFu;
    for (size_t i = 0; i < len; i++) {
        crc ^= (uint32_t)data[i] << 24;
        for (int bit = 0; bit < 8; bit++)
            crc = (crc & 0x80000000u) ? (crc << 1) ^ 0x04C11DB7u : crc << 1;
    }
    return crc;
}

static uint16_t get16(const uint8_t *p) { return (uint16_t)(p[0] | p[1] << 8); }
static void put16(uint8_t *p, uint16_t v) { p[0] = v & 0xFF; p[1] = v >> 8; }

static void send_packet(const char *id, const uint8_t *payload, uint16_t size)
{
    uint8_t buf[MAX_PACKET];
    memcpy(buf, id, 4);
    put16(buf + 4, 0);              /* revision */
    put16(buf + 6, 0);              /* origin: controllers send 0 */
    put16(buf + 8, out_serial++);
    put16(buf + 10, size);
    memset(buf + 12, 0, 4);         /* spare */
    memcpy(buf + PREFIX_LEN, payload, size);
    uint32_t crc = crc32_mpeg2(buf, PREFIX_LEN + size);
    for (int i = 0; i < 4; i++)
        buf[PREFIX_LEN + size + i] = (uint8_t)(crc >> (8 * i));
    sendto(sock, buf, PREFIX_LEN + size + 4, 0, (struct sockaddr *)&peer, sizeof peer);
}

static void send_vrpo(void)
{
    static uint16_t number;
    uint8_t payload[2 + 32];
    put16(payload, number++);
    for (int i = 0; i < 32; i++)
        payload[2 + i] = (uint8_t)i;
    send_packet("VRPO", payload, sizeof payload);
}

static void send_vrco(void)
{
    uint8_t payload[COMMAND_SIZE] = {0};
    put16(payload, vrco.id);
    memcpy(payload + 6, "ALARM", 5);
    send_packet("VRCO", payload, sizeof payload);
    vrco.last = now_ms();
}

/* --- VRPI ----------------------------------------------------------------------------------- */
static uint8_t *laps;               /* one flag per VLAP seen: VLAPS counts 0..3 */

static uint8_t *lap_slot(int vlaps) { return vlaps < 4 ? laps + vlaps : NULL; }

static void record_laps(int vlaps)
{
    if (!laps && !(laps = malloc(4)))
        return;
#ifdef BUG_HEAP_OVERFLOW
    memset(laps, 1, (size_t)vlaps + 1);
#else
    memset(laps, 1, vlaps < 4 ? (size_t)vlaps + 1 : 4);
#endif
#ifdef BUG_LAP_SLOT
    *lap_slot(vlaps) = 2;            /* the last VLAP seen: NULL unchecked */
#else
    uint8_t *last = lap_slot(vlaps);
    if (last)
        *last = 2;
#endif
}

static void on_initial(void) { state.ru_armed = 0; }
static void on_stopped(void) { state.ru_armed = 0; }
static void on_disarmed(void) { state.ru_armed = 0; }
static void on_armed(void) { }

typedef void (*state_handler)(void);
static state_handler handlers[256] = {
    [0x00] = on_initial, [0x01] = on_stopped, [0x02] = on_stopped, [0x03] = on_stopped,
    [0x04] = on_stopped, [0x10] = on_disarmed, [0x11] = on_armed,
};

static void dispatch_state(int bu_state)
{
    state_handler handler = handlers[bu_state & 0xFF];
#ifndef BUG_NULL_CALL
    if (!handler)
        return;                      /* an unknown state changes nothing */
#endif
    handler();
}

static void on_vrpi(const uint8_t *p)
{
    state.bu_state = p[0];
    dispatch_state(p[0]);
    record_laps(p[1]);
    uint16_t armed_ru = get16(p + 6);
    state.ru_armed = p[0] == 0x11 && armed_ru != 0 && (p[8] == 2 || p[8] == 3);
}

/* --- commands ------------------------------------------------------------------------------- */
static int retransmission(uint16_t id, int64_t now)
{
    for (int i = 0; i < IDS_KEPT; i++)
        if (heard[i].at && heard[i].id == id && now - heard[i].at < REUSE_GAP_MS) {
            heard[i].at = now;
            return 1;
        }
    heard[heard_next].id = id;
    heard[heard_next].at = now;
    heard_next = (heard_next + 1) % IDS_KEPT;
    return 0;
}

static void maintenance_engage(const uint8_t *data)
{
#ifdef BUG_DEEP
    volatile uint8_t *log_line = NULL;   /* the maintenance log was never opened */
    log_line[0] = data[6];
#else
    (void)data;
#endif
    state.executed++;
}

static void execute(const uint8_t *data)
{
    if (memcmp(data, "MAINT:", 6) == 0) {
        state.maintenance = 1;
        return;
    }
    if (state.maintenance) {
        state.maintenance = 0;
        if (memcmp(data, "ENGAGE", 6) == 0)
            maintenance_engage(data);
        return;
    }
    if (state.ru_armed)
        state.executed++;
}

#if defined(BUG_LEAK) || defined(CHURN) || defined(BUG_LEAK_UNKNOWN)
static void *leak_64k(void)
{
    static void *volatile kept;
    kept = malloc(64 * 1024);
    if (kept)
        memset(kept, 1, 64 * 1024);           /* written: resident */
    return kept;
}
#endif

static void on_vrci(const uint8_t *p)
{
    uint16_t id = get16(p);
#ifdef BUG_ABORT
    if (id == 0xFFFF)
        abort();
#endif
#ifdef BUG_LEAK
    leak_64k();                               /* each command's log buffer */
#elif defined(CHURN)
    free(leak_64k());
#endif
    uint8_t ack[ACK_SIZE];
    put16(ack, id);
    send_packet("VRAO", ack, sizeof ack);
    if (!retransmission(id, now_ms()))
        execute(p + 6);
}

static void on_vrai(const uint8_t *p)
{
    if (vrco.in_flight && get16(p) == vrco.id)
        vrco.in_flight = 0;
}

/* --- framing ------------------------------------------------------------------------------- */
static void on_datagram(const uint8_t *buf, ssize_t len)
{
    if (len < OVERHEAD || len > MAX_PACKET)
        return;                      /* also: size above 492 */
    uint16_t size = get16(buf + 10);
    if (get16(buf + 4) != 0 || (ssize_t)size + OVERHEAD != len)
        return;
    uint32_t stored = buf[PREFIX_LEN + size] | buf[PREFIX_LEN + size + 1] << 8
        | buf[PREFIX_LEN + size + 2] << 16 | (uint32_t)buf[PREFIX_LEN + size + 3] << 24;
    if (stored != crc32_mpeg2(buf, PREFIX_LEN + size))
        return;
    const uint8_t *payload = buf + PREFIX_LEN;
    /* A payload longer than the type's layout is legal (the rest is for later revisions). */
    if (memcmp(buf, "VRPI", 4) == 0 && size >= VRPI_SIZE)
        on_vrpi(payload);
    else if (memcmp(buf, "VRCI", 4) == 0 && size >= COMMAND_SIZE)
        on_vrci(payload);
    else if (memcmp(buf, "VRAI", 4) == 0 && size >= ACK_SIZE)
        on_vrai(payload);
#ifdef BUG_LEAK_UNKNOWN
    else if (memcmp(buf, "VRPI", 4) && memcmp(buf, "VRCI", 4) && memcmp(buf, "VRAI", 4) && memcmp(buf, "VRPO", 4)
             && memcmp(buf, "VRCO", 4) && memcmp(buf, "VRAO", 4))
        leak_64k();                          /* the packet kept for a handler no ID has */
#endif
}

static void on_term(int sig) { (void)sig; stopping = 1; }

int main(int argc, char **argv)
{
    if (argc != 3) {
        fprintf(stderr, "usage: %s LISTEN_PORT PEER_PORT\n", argv[0]);
        return 2;
    }
    struct sockaddr_in me = {.sin_family = AF_INET, .sin_port = htons((uint16_t)atoi(argv[1]))};
    me.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    peer = me;
    peer.sin_port = htons((uint16_t)atoi(argv[2]));
    sock = socket(AF_INET, SOCK_DGRAM, 0);
    if (sock < 0 || bind(sock, (struct sockaddr *)&me, sizeof me) < 0) {
        perror("controller: bind");
        return 1;
    }
    signal(SIGTERM, on_term);
    fprintf(stderr, "controller: listening on 127.0.0.1:%s\n", argv[1]);
    int64_t next_vrpo = now_ms(), next_command = now_ms() + 1000;
    while (!stopping) {
        int64_t now = now_ms();
        if (now >= next_vrpo) {
            send_vrpo();
            next_vrpo += 100;
            if (next_vrpo <= now)
                next_vrpo = now + 100;
        }
        if (!vrco.in_flight && now >= next_command) {
            vrco.in_flight = 1;
            vrco.id = vrco_next_id++;
            vrco.first = now;
            send_vrco();
            next_command = now + 1000;
        } else if (vrco.in_flight && now - vrco.first >= 2000) {
            vrco.in_flight = 0;      /* given up */
        } else if (vrco.in_flight && now - vrco.last >= 100) {
            send_vrco();
        }
        int64_t wake = next_vrpo;
        if (vrco.in_flight && vrco.last + 100 < wake)
            wake = vrco.last + 100;
        struct pollfd pfd = {.fd = sock, .events = POLLIN};
        int timeout = (int)(wake - now_ms());
        if (poll(&pfd, 1, timeout < 0 ? 0 : timeout) > 0) {
            uint8_t buf[2048];
            ssize_t len;
            while ((len = recv(sock, buf, sizeof buf, MSG_DONTWAIT)) >= 0)
                on_datagram(buf, len);
        }
    }
    fprintf(stderr, "controller: stopping, %ld commands executed\n", state.executed);
    return 0;
}
