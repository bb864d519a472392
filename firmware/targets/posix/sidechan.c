/* The simulator's "hardware" side channel: a Unix stream socket publishing newline-delimited
 * JSON (one object per line) to any number of clients, and accepting camera edges from them.
 *
 * Writes apply back-pressure rather than dropping lines: a test that counts events must see
 * every one of them, even in speed-0 runs that produce thousands of lines at once. A client that
 * stops reading for SIDECHAN_STALL_MS is disconnected so it cannot freeze the simulator. */
#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <unistd.h>

#include "sim.h"

#define SIDECHAN_LINE_MAX 256
#define SIDECHAN_STALL_MS 2000

typedef struct {
    int fd;                           /* -1 = free slot */
    char in[SIDECHAN_LINE_MAX];
    size_t in_len;
    int discarding;                   /* an over-long input line is being skipped */
} client_t;

static int listen_fd = -1;
static char sock_path[sizeof(((struct sockaddr_un *)0)->sun_path)];
static client_t clients[SIDECHAN_MAX_CLIENTS];

static void set_nonblock(int fd)
{
    int fl = fcntl(fd, F_GETFL, 0);
    if (fl >= 0) {
        (void)fcntl(fd, F_SETFL, fl | O_NONBLOCK);
    }
}

int sidechan_open(const char *path)
{
    for (int i = 0; i < SIDECHAN_MAX_CLIENTS; i++) {
        clients[i].fd = -1;
    }
    struct sockaddr_un sa;
    memset(&sa, 0, sizeof sa);
    sa.sun_family = AF_UNIX;
    if (strlen(path) >= sizeof sa.sun_path) {
        fprintf(stderr, "dualscale-sim: --hw-socket path too long: %s\n", path);
        return -1;
    }
    strcpy(sa.sun_path, path);

    /* A socket file left by a killed run would make bind() fail; remove it, but never a
     * regular file somebody put there by mistake. */
    struct stat st;
    if (lstat(path, &st) == 0 && S_ISSOCK(st.st_mode)) {
        (void)unlink(path);
    }
    listen_fd = socket(AF_UNIX, SOCK_STREAM, 0);
    if (listen_fd < 0) {
        perror("dualscale-sim: socket");
        return -1;
    }
    if (bind(listen_fd, (struct sockaddr *)&sa, sizeof sa) != 0 || listen(listen_fd, 8) != 0) {
        perror("dualscale-sim: bind/listen on --hw-socket");
        close(listen_fd);
        listen_fd = -1;
        return -1;
    }
    set_nonblock(listen_fd);
    strcpy(sock_path, path);
    return 0;
}

static void drop_client(client_t *cl)
{
    close(cl->fd);
    cl->fd = -1;
    cl->in_len = 0;
    cl->discarding = 0;
}

void sidechan_close(void)
{
    for (int i = 0; i < SIDECHAN_MAX_CLIENTS; i++) {
        if (clients[i].fd >= 0) {
            drop_client(&clients[i]);
        }
    }
    if (listen_fd >= 0) {
        close(listen_fd);
        listen_fd = -1;
        (void)unlink(sock_path);
    }
}

int sidechan_enabled(void)
{
    return listen_fd >= 0;
}

int sidechan_fill_fds(fd_set *readfds)
{
    int maxfd = -1;
    if (listen_fd < 0) {
        return maxfd;
    }
    FD_SET(listen_fd, readfds);
    maxfd = listen_fd;
    for (int i = 0; i < SIDECHAN_MAX_CLIENTS; i++) {
        if (clients[i].fd >= 0) {
            FD_SET(clients[i].fd, readfds);
            if (clients[i].fd > maxfd) {
                maxfd = clients[i].fd;
            }
        }
    }
    return maxfd;
}

/* Minimal field extraction for the few flat messages we accept; not a general JSON parser.
 * Returns a pointer just past `"key"` and the colon, or NULL. */
static const char *json_field(const char *line, const char *key)
{
    char pat[32];
    int n = snprintf(pat, sizeof pat, "\"%s\"", key);
    if (n <= 0 || (size_t)n >= sizeof pat) {
        return NULL;
    }
    const char *p = strstr(line, pat);
    if (p == NULL) {
        return NULL;
    }
    p += n;
    while (*p == ' ' || *p == '\t') {
        p++;
    }
    if (*p != ':') {
        return NULL;
    }
    p++;
    while (*p == ' ' || *p == '\t') {
        p++;
    }
    return p;
}

static void handle_line(client_t *cl, char *line, sidechan_edge_fn on_edge, void *ctx)
{
    const char *ev = json_field(line, "ev");
    if (ev != NULL && strncmp(ev, "\"edge\"", 6) == 0) {
        const char *cam = json_field(line, "camera");
        char *end = NULL;
        long c = cam != NULL ? strtol(cam, &end, 10) : -1;
        if (cam != NULL && end != cam && c >= 0 && c < 256) {
            on_edge(ctx, (uint8_t)c);
            return;
        }
    }
    if (line[0] == '\0') {
        return; /* blank lines are harmless */
    }
    static const char err[] = "{\"ev\":\"error\",\"msg\":\"expected {\\\"ev\\\":\\\"edge\\\",\\\"camera\\\":N}\"}";
    sidechan_send(cl->fd, err, sizeof err - 1);
}

void sidechan_service(const fd_set *readfds, sidechan_edge_fn on_edge, sidechan_hello_fn on_hello,
                      void *ctx)
{
    if (listen_fd < 0) {
        return;
    }
    if (FD_ISSET(listen_fd, readfds)) {
        for (;;) {
            int fd = accept(listen_fd, NULL, NULL);
            if (fd < 0) {
                break;
            }
            int slot = -1;
            for (int i = 0; i < SIDECHAN_MAX_CLIENTS; i++) {
                if (clients[i].fd < 0) {
                    slot = i;
                    break;
                }
            }
            if (slot < 0) {
                static const char full[] = "{\"ev\":\"error\",\"msg\":\"too many clients\"}\n";
                (void)!write(fd, full, sizeof full - 1);
                close(fd);
                continue;
            }
            set_nonblock(fd);
            clients[slot].fd = fd;
            clients[slot].in_len = 0;
            clients[slot].discarding = 0;
            if (on_hello != NULL) {
                on_hello(ctx, fd);
            }
        }
    }
    for (int i = 0; i < SIDECHAN_MAX_CLIENTS; i++) {
        client_t *cl = &clients[i];
        if (cl->fd < 0 || !FD_ISSET(cl->fd, readfds)) {
            continue;
        }
        char buf[512];
        ssize_t n = read(cl->fd, buf, sizeof buf);
        if (n == 0 || (n < 0 && errno != EAGAIN && errno != EINTR)) {
            drop_client(cl);
            continue;
        }
        for (ssize_t k = 0; k < n && cl->fd >= 0; k++) {
            char ch = buf[k];
            if (ch == '\n') {
                if (!cl->discarding) {
                    cl->in[cl->in_len] = '\0';
                    handle_line(cl, cl->in, on_edge, ctx);
                }
                cl->in_len = 0;
                cl->discarding = 0;
            } else if (cl->in_len + 1 < sizeof cl->in) {
                cl->in[cl->in_len++] = ch;
            } else {
                cl->discarding = 1;
            }
        }
    }
}

/* Write all of buf to one client, waiting while its socket buffer is full. */
static int send_all(int fd, const char *buf, size_t len)
{
    while (len > 0) {
        ssize_t n = write(fd, buf, len);
        if (n > 0) {
            buf += n;
            len -= (size_t)n;
            continue;
        }
        if (n < 0 && errno == EINTR) {
            continue;
        }
        if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
            struct pollfd p = {.fd = fd, .events = POLLOUT, .revents = 0};
            if (poll(&p, 1, SIDECHAN_STALL_MS) > 0 && (p.revents & POLLOUT)) {
                continue;
            }
        }
        return -1;
    }
    return 0;
}

void sidechan_send(int fd, const char *line, size_t len)
{
    char buf[SIDECHAN_LINE_MAX + 1];
    if (len > SIDECHAN_LINE_MAX) {
        len = SIDECHAN_LINE_MAX;
    }
    memcpy(buf, line, len);
    buf[len] = '\n';
    for (int i = 0; i < SIDECHAN_MAX_CLIENTS; i++) {
        client_t *cl = &clients[i];
        if (cl->fd < 0 || (fd >= 0 && cl->fd != fd)) {
            continue;
        }
        if (send_all(cl->fd, buf, len + 1) != 0) {
            drop_client(cl);
        }
    }
}
