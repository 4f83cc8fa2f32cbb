/*
 * sim_link.c - the virtual device's serial link.
 *
 * TX: the core writes into an 8 KiB ring (SIM_TX_RING), like a real UART driver's buffer.
 * The "UART" shifts bytes out of it at baud/10 bytes per second of DEVICE time (pure
 * arithmetic, updated whenever device time moves: no syscall per tick). Shifted-out bytes
 * are handed to the OS endpoint in batches by the main loop (sim_link_flush). When the
 * endpoint is full (the host does not read), shifted-out bytes wait in a staging area
 * (up to SIM_TX_STORE - SIM_TX_RING bytes); once that is full the UART stops, the ring
 * fills, link_tx_free() shrinks and the core drops whole batches and counts them: the
 * device never blocks and no frame is cut.
 *
 * Endpoints: a pseudo-terminal (posix_openpt; we keep the slave open ourselves, in raw
 * mode, so the pty persists and writes never fail with EIO while no client has it open)
 * and/or a TCP listener on 127.0.0.1 accepting one client at a time (a new client
 * replaces the old one). The wire goes to the TCP client when one is connected, otherwise
 * to the pty; with neither, shifted-out bytes are discarded (a UART with nothing
 * attached). Bytes received from either endpoint go to one RX ring read by link_read().
 *
 * Faults on the wire (applied as bytes leave for the OS): drop the next N bytes, or flip
 * one random bit in each of the next N bytes.
 */
#define _GNU_SOURCE
#include "sim.h"

#include <arpa/inet.h>
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <termios.h>
#include <unistd.h>

#define TX_MASK (SIM_TX_STORE - 1u)
#define RX_MASK (SIM_RX_RING - 1u)
#define STAGE_MAX (SIM_TX_STORE - SIM_TX_RING)

static int set_nonblock(int fd)
{
    int fl = fcntl(fd, F_GETFL);
    return fl < 0 ? -1 : fcntl(fd, F_SETFL, fl | O_NONBLOCK);
}

static int open_pty(sim_link_t *l)
{
    int m = posix_openpt(O_RDWR | O_NOCTTY | O_CLOEXEC);
    if (m < 0 || grantpt(m) != 0 || unlockpt(m) != 0) {
        sim_log("link: cannot create a pty: %s", strerror(errno));
        if (m >= 0) {
            close(m);
        }
        return -1;
    }
    if (ptsname_r(m, l->pty_name, sizeof l->pty_name) != 0) {
        sim_log("link: ptsname failed");
        close(m);
        return -1;
    }
    int s = open(l->pty_name, O_RDWR | O_NOCTTY | O_CLOEXEC | O_NONBLOCK);
    if (s < 0) {
        sim_log("link: cannot open %s: %s", l->pty_name, strerror(errno));
        close(m);
        return -1;
    }
    struct termios tio;
    if (tcgetattr(s, &tio) == 0) {
        cfmakeraw(&tio);
        tcsetattr(s, TCSANOW, &tio);
    }
    set_nonblock(m);
    l->pty_master = m;
    l->pty_slave = s;
    return 0;
}

int sim_listen_tcp(int port, int *bound_port)
{
    int fd = socket(AF_INET, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
    if (fd < 0) {
        return -1;
    }
    int one = 1;
    setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
    struct sockaddr_in a;
    memset(&a, 0, sizeof a);
    a.sin_family = AF_INET;
    a.sin_port = htons((uint16_t)port);
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    if (bind(fd, (struct sockaddr *)&a, sizeof a) != 0 || listen(fd, 4) != 0) {
        int e = errno;
        close(fd);
        errno = e;
        return -1;
    }
    socklen_t al = sizeof a;
    if (getsockname(fd, (struct sockaddr *)&a, &al) != 0) {
        close(fd);
        return -1;
    }
    *bound_port = ntohs(a.sin_port);
    return fd;
}

int sim_link_open(sim_link_t *l, int want_pty, int tcp_port, uint32_t baud)
{
    memset(l, 0, sizeof *l);
    l->pty_master = l->pty_slave = l->tcp_listen = l->tcp_client = -1;
    l->tcp_port = -1;
    l->bytes_per_us = (double)baud / 10.0 / 1e6;
    if (want_pty && open_pty(l) != 0) {
        return -1;
    }
    if (tcp_port >= 0) {
        l->tcp_listen = sim_listen_tcp(tcp_port, &l->tcp_port);
        if (l->tcp_listen < 0) {
            sim_log("link: cannot listen on 127.0.0.1:%d: %s", tcp_port, strerror(errno));
            return -1;
        }
    }
    return 0;
}

static void close_fd(int *fd)
{
    if (*fd >= 0) {
        close(*fd);
        *fd = -1;
    }
}

void sim_link_close(sim_link_t *l)
{
    close_fd(&l->tcp_client);
    close_fd(&l->tcp_listen);
    close_fd(&l->pty_slave);
    close_fd(&l->pty_master);
}

void sim_link_reset(sim_link_t *l, uint64_t t_us)
{
    l->tx_head = l->tx_uart = l->tx_fault = l->tx_os = 0;
    l->uart_credit = 0.0;
    l->uart_t_us = t_us;
    l->rx_head = l->rx_tail = 0;
    l->os_blocked = 0;
}

void sim_link_uart_update(sim_link_t *l, uint64_t t_us)
{
    if (t_us <= l->uart_t_us) {
        return;
    }
    uint64_t queued = l->tx_head - l->tx_uart;
    if (queued == 0) { /* idle UART: no credit builds up */
        l->uart_t_us = t_us;
        l->uart_credit = 0.0;
        return;
    }
    l->uart_credit += (double)(t_us - l->uart_t_us) * l->bytes_per_us;
    l->uart_t_us = t_us;
    uint64_t room = l->tx_os + STAGE_MAX - l->tx_uart;
    uint64_t can = l->uart_credit >= 1e18 ? UINT64_MAX : (uint64_t)l->uart_credit;
    uint64_t n = can < queued ? can : queued;
    if (n > room) {
        n = room;
    }
    l->tx_uart += n;
    l->uart_credit -= (double)n;
    if (l->tx_uart == l->tx_head || n == room) {
        l->uart_credit -= floor(l->uart_credit); /* stalled or empty: keep the fraction only */
    }
}

size_t sim_link_queued(const sim_link_t *l) { return (size_t)(l->tx_head - l->tx_uart); }

size_t sim_link_staged(const sim_link_t *l) { return (size_t)(l->tx_uart - l->tx_os); }

size_t sim_link_tx_free(sim_link_t *l) { return SIM_TX_RING - sim_link_queued(l); }

uint64_t sim_link_next_drain_us(const sim_link_t *l)
{
    size_t q = sim_link_queued(l);
    if (q == 0 || !(l->bytes_per_us > 0.0)) {
        return 0;
    }
    return (uint64_t)ceil((double)q / l->bytes_per_us);
}

size_t sim_link_write(sim_link_t *l, const uint8_t *data, size_t len)
{
    size_t free_b = sim_link_tx_free(l);
    size_t n = len < free_b ? len : free_b;
    /* true whenever the ring has less room than len (cppcheck 2.10 misreads the min above) */
    // cppcheck-suppress knownConditionTrueFalse
    if (n < len) {
        l->tx_refused += len - n;
    }
    size_t start = (size_t)(l->tx_head & TX_MASK);
    size_t first = SIM_TX_STORE - start < n ? SIM_TX_STORE - start : n;
    memcpy(l->tx + start, data, first);
    memcpy(l->tx, data + first, n - first);
    l->tx_head += n;
    return n;
}

size_t sim_link_read(sim_link_t *l, uint8_t *buf, size_t cap)
{
    size_t n = 0;
    while (n < cap && l->rx_tail != l->rx_head) {
        buf[n++] = l->rx[l->rx_tail++ & RX_MASK];
    }
    return n;
}

static void drop_client(sim_link_t *l, const char *why)
{
    if (l->tcp_client >= 0) {
        sim_log("link: TCP client gone (%s)", why);
        close_fd(&l->tcp_client);
    }
}

int sim_link_accept(sim_link_t *l)
{
    int c = accept4(l->tcp_listen, NULL, NULL, SOCK_NONBLOCK | SOCK_CLOEXEC);
    if (c < 0) {
        return -1;
    }
    if (l->tcp_client >= 0) {
        sim_log("link: a new TCP client replaces the previous one");
        close_fd(&l->tcp_client);
    }
    int one = 1;
    setsockopt(c, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
    l->tcp_client = c;
    l->clients_accepted++;
    l->conn_rx = l->conn_tx = 0;
    /* bytes already on the wire were meant for the previous client */
    l->bytes_discarded += l->tx_uart - l->tx_os;
    l->tx_os = l->tx_uart;
    if (l->tx_fault < l->tx_os) {
        l->tx_fault = l->tx_os;
    }
    l->os_blocked = 0;
    return 0;
}

void sim_link_flush(sim_link_t *l)
{
    l->os_blocked = 0;
    while (l->tx_os < l->tx_uart) {
        uint64_t avail = l->tx_uart - l->tx_os;
        if (l->drop_remaining > 0) {
            uint64_t k = avail < l->drop_remaining ? avail : l->drop_remaining;
            l->tx_os += k;
            l->drop_remaining -= (uint32_t)k;
            l->bytes_dropped += k;
            if (l->tx_fault < l->tx_os) {
                l->tx_fault = l->tx_os;
            }
            continue;
        }
        int fd = l->tcp_client >= 0 ? l->tcp_client : l->pty_master;
        if (fd < 0) {
            l->bytes_discarded += avail;
            l->tx_os = l->tx_uart;
            break;
        }
        size_t start = (size_t)(l->tx_os & TX_MASK);
        size_t seg = (size_t)(avail < SIM_TX_STORE - start ? avail : SIM_TX_STORE - start);
        if (l->flip_remaining > 0) {
            uint64_t from = l->tx_fault > l->tx_os ? l->tx_fault : l->tx_os;
            uint64_t to = from + l->flip_remaining;
            if (to > l->tx_os + seg) {
                to = l->tx_os + seg;
            }
            for (uint64_t i = from; i < to; i++) {
                l->tx[i & TX_MASK] ^= (uint8_t)(1u << (sim_rng_u64(&l->fault_rng) >> 61));
            }
            if (to > from) {
                l->flip_remaining -= (uint32_t)(to - from);
                l->bytes_flipped += to - from;
                l->tx_fault = to;
            }
        }
        ssize_t n = fd == l->tcp_client ? send(fd, l->tx + start, seg, MSG_NOSIGNAL)
                                        : write(fd, l->tx + start, seg);
        if (n > 0) {
            l->tx_os += (uint64_t)n;
            l->bytes_written_os += (uint64_t)n;
            l->conn_tx += (uint64_t)n;
            continue;
        }
        if (n < 0 && errno == EINTR) {
            continue;
        }
        if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
            l->os_blocked = 1;
            break;
        }
        if (fd == l->tcp_client) {
            drop_client(l, n < 0 ? strerror(errno) : "write returned 0");
            continue;
        }
        /* pty: EIO (no slave) or another error: the bytes go nowhere */
        l->bytes_discarded += seg;
        l->tx_os += seg;
    }
    if (l->tx_fault < l->tx_os) {
        l->tx_fault = l->tx_os;
    }
}

static int read_into_rx(sim_link_t *l, int fd, int is_tcp)
{
    for (;;) {
        uint32_t used = l->rx_head - l->rx_tail;
        if (used >= SIM_RX_RING) {
            return 0; /* the core has not read yet: leave the rest in the OS */
        }
        size_t start = l->rx_head & RX_MASK;
        size_t room = SIM_RX_RING - used;
        if (room > SIM_RX_RING - start) {
            room = SIM_RX_RING - start;
        }
        ssize_t n = is_tcp ? recv(fd, l->rx + start, room, 0) : read(fd, l->rx + start, room);
        if (n > 0) {
            l->rx_head += (uint32_t)n;
            l->bytes_received += (uint64_t)n;
            l->conn_rx += (uint64_t)n;
            continue;
        }
        if (n < 0 && errno == EINTR) {
            continue;
        }
        if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
            return 0;
        }
        return -1; /* EOF or error */
    }
}

void sim_link_receive(sim_link_t *l)
{
    if (l->tcp_client >= 0 && read_into_rx(l, l->tcp_client, 1) < 0) {
        drop_client(l, "closed by the host");
    }
    if (l->pty_master >= 0) {
        read_into_rx(l, l->pty_master, 0); /* EIO (no slave) cannot happen: we hold one */
    }
}
