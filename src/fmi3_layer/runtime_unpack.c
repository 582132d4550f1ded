/* Unpacking the runtime an FMU carries (see runtime_unpack.h for why and where). */
#define _GNU_SOURCE
#include "runtime_unpack.h"

#include <dlfcn.h>
#include <errno.h>
#include <fcntl.h>
#include <ftw.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>
#include <zlib.h> /* z_stream's layout and constants only: the functions are loaded at run time */

typedef struct {
    int (*inflateInit2_)(z_streamp, int, const char *, int);
    int (*inflate)(z_streamp, int);
    int (*inflateEnd)(z_streamp);
    uLong (*crc32)(uLong, const Bytef *, uInt);
} Zlib;

static int load_zlib(Zlib *z, char *reason, size_t reason_size) {
    void *handle = dlopen("libz.so.1", RTLD_NOW | RTLD_LOCAL);
    if (!handle) {
        snprintf(reason, reason_size, "zlib (libz.so.1) is needed once to unpack the FMU's Python runtime and is "
                 "not on this machine (%s): install it (Debian/Ubuntu: zlib1g; Fedora/RHEL: zlib)", dlerror());
        return -1;
    }
    *(void **)&z->inflateInit2_ = dlsym(handle, "inflateInit2_");
    *(void **)&z->inflate = dlsym(handle, "inflate");
    *(void **)&z->inflateEnd = dlsym(handle, "inflateEnd");
    *(void **)&z->crc32 = dlsym(handle, "crc32");
    if (!z->inflateInit2_ || !z->inflate || !z->inflateEnd || !z->crc32) {
        snprintf(reason, reason_size, "libz.so.1 lacks inflate or crc32: a damaged zlib installation");
        return -1;
    }
    return 0;
}

static uint16_t u16(const unsigned char *p) { return (uint16_t)(p[0] | p[1] << 8); }
static uint32_t u32(const unsigned char *p) { return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24; }

/* A name inside the archive that stays inside the folder: relative, no "..", no empty part. */
static int safe_name(const char *name, size_t length) {
    if (length == 0 || name[0] == '/' || memchr(name, '\0', length) || memchr(name, '\\', length)) return 0;
    const char *part = name, *end = name + length;
    while (part < end) {
        const char *slash = memchr(part, '/', (size_t)(end - part));
        size_t n = slash ? (size_t)(slash - part) : (size_t)(end - part);
        if ((n == 0 && slash && slash + 1 != end) || (n == 2 && part[0] == '.' && part[1] == '.') ||
            (n == 1 && part[0] == '.'))
            return 0;
        part += n + 1;
    }
    return 1;
}

static int make_parents(char *path) {
    for (char *p = path + 1; *p; p++) {
        if (*p != '/') continue;
        *p = '\0';
        int failed = mkdir(path, 0755) != 0 && errno != EEXIST;
        *p = '/';
        if (failed) return -1;
    }
    return 0;
}

static int write_entry(const Zlib *z, const unsigned char *data, uint32_t packed, uint32_t size, int method,
                       uint32_t crc, const char *path, mode_t mode, char *reason, size_t reason_size) {
    unsigned char *out = malloc(size ? size : 1);
    if (!out) {
        snprintf(reason, reason_size, "out of memory unpacking %s", path);
        return -1;
    }
    if (method == 0) {
        if (packed != size) goto damaged;
        memcpy(out, data, size);
    } else {
        z_stream stream;
        memset(&stream, 0, sizeof stream);
        if (z->inflateInit2_(&stream, -MAX_WBITS, ZLIB_VERSION, (int)sizeof stream) != Z_OK) goto damaged;
        stream.next_in = (Bytef *)data;
        stream.avail_in = packed;
        stream.next_out = out;
        stream.avail_out = size;
        int status = z->inflate(&stream, Z_FINISH);
        z->inflateEnd(&stream);
        if (status != Z_STREAM_END || stream.total_out != size) goto damaged;
    }
    if (z->crc32(0L, out, size) != crc) goto damaged;
    int fd = open(path, O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, mode);
    if (fd < 0) {
        snprintf(reason, reason_size, "cannot write %s (%s)", path, strerror(errno));
        free(out);
        return -1;
    }
    size_t written = 0;
    while (written < size) {
        ssize_t n = write(fd, out + written, size - written);
        if (n <= 0) {
            snprintf(reason, reason_size, "cannot write %s (%s)", path, strerror(errno));
            close(fd);
            free(out);
            return -1;
        }
        written += (size_t)n;
    }
    free(out);
    return close(fd);
damaged:
    snprintf(reason, reason_size, "%s in the FMU's runtime.zip is damaged (it does not inflate to its recorded "
             "size and checksum): the FMU is damaged; use an intact copy or build it again", path);
    free(out);
    return -1;
}

/* Unpack the zip `archive` into the existing folder `dest`. */
static int unpack(const char *archive, const char *dest, char *reason, size_t reason_size) {
    Zlib z;
    if (load_zlib(&z, reason, reason_size) != 0) return -1;
    int fd = open(archive, O_RDONLY | O_CLOEXEC);
    struct stat st;
    if (fd < 0 || fstat(fd, &st) != 0) {
        snprintf(reason, reason_size, "cannot read %s (%s)", archive, strerror(errno));
        if (fd >= 0) close(fd);
        return -1;
    }
    size_t length = (size_t)st.st_size;
    const unsigned char *zip = length >= 22 ? mmap(NULL, length, PROT_READ, MAP_PRIVATE, fd, 0) : MAP_FAILED;
    close(fd);
    if (zip == MAP_FAILED) {
        snprintf(reason, reason_size, "%s is not a zip archive: the FMU is damaged; build it again", archive);
        return -1;
    }
    int result = -1;
    /* the end-of-central-directory record: the last signature within the final 64 KiB + 22 bytes */
    const unsigned char *end = NULL;
    for (size_t back = 22; back <= length && back <= 22 + 65535 && !end; back++)
        if (u32(zip + length - back) == 0x06054b50u) end = zip + length - back;
    if (!end) goto damaged;
    uint16_t entries = u16(end + 10);
    uint32_t directory_size = u32(end + 12), directory = u32(end + 16);
    if ((uint64_t)directory + directory_size > (uint64_t)(end - zip)) goto damaged;
    const unsigned char *entry = zip + directory, *directory_end = zip + directory + directory_size;
    char path[8192];
    for (uint16_t i = 0; i < entries; i++) {
        if (entry + 46 > directory_end || u32(entry) != 0x02014b50u) goto damaged;
        int method = u16(entry + 10);
        uint32_t crc = u32(entry + 16), packed = u32(entry + 20), size = u32(entry + 24);
        uint16_t name_length = u16(entry + 28), extra = u16(entry + 30), comment = u16(entry + 32);
        uint32_t external = u32(entry + 38), local = u32(entry + 42);
        const char *name = (const char *)entry + 46;
        if (entry + 46 + name_length > directory_end || !safe_name(name, name_length)) goto damaged;
        if ((method != 0 && method != 8) || (u16(entry + 8) & 1) /* encrypted */) goto damaged;
        if ((uint64_t)local + 30 > length || u32(zip + local) != 0x04034b50u) goto damaged;
        uint64_t data = (uint64_t)local + 30 + u16(zip + local + 26) + u16(zip + local + 28);
        if (data + packed > length) goto damaged;
        if (snprintf(path, sizeof path, "%s/%.*s", dest, (int)name_length, name) >= (int)sizeof path) {
            snprintf(reason, reason_size, "the path of the runtime in %s is too long", dest);
            goto done;
        }
        if (make_parents(path) != 0) {
            snprintf(reason, reason_size, "cannot make the folders of %s (%s)", path, strerror(errno));
            goto done;
        }
        mode_t mode = (external >> 16) & 0777;
        if (name[name_length - 1] == '/') {
            if (mkdir(path, 0755) != 0 && errno != EEXIST) {
                snprintf(reason, reason_size, "cannot make %s (%s)", path, strerror(errno));
                goto done;
            }
        } else if (S_ISLNK(external >> 16)) {
            goto damaged; /* the build writes no links */
        } else if (write_entry(&z, zip + data, packed, size, method, crc, path, mode ? mode : 0644, reason,
                               reason_size) != 0) {
            goto done;
        }
        entry += 46 + name_length + extra + comment;
    }
    result = 0;
    goto done;
damaged:
    snprintf(reason, reason_size, "%s is not a complete runtime archive: the FMU is damaged; use an intact copy "
             "or build it again (python -m orchestration build)", archive);
done:
    munmap((void *)zip, length);
    return result;
}

static int remove_one(const char *path, const struct stat *st, int flag, struct FTW *ftw) {
    (void)st; (void)flag; (void)ftw;
    return remove(path);
}

static int read_id(const char *resource_dir, char *id, size_t size) {
    char file[4096];
    snprintf(file, sizeof file, "%s/runtime.id", resource_dir);
    FILE *f = fopen(file, "r");
    id[0] = '\0';
    if (!f) return -1;
    if (fgets(id, (int)size, f)) id[strcspn(id, "\r\n")] = '\0';
    fclose(f);
    for (const char *c = id; *c; c++)
        if (!((*c >= '0' && *c <= '9') || (*c >= 'a' && *c <= 'f'))) return -1;
    return id[0] ? 0 : -1;
}

static int is_complete(const char *folder) {
    char manifest[4200];
    snprintf(manifest, sizeof manifest, "%s/manifest.txt", folder);
    return access(manifest, R_OK) == 0;
}

/* Unpack into `parent`/`id` (made complete by a rename); 0 when it is there now. */
static int unpack_into(const char *archive, const char *parent, const char *id, char *folder, size_t folder_size,
                       char *reason, size_t reason_size) {
    snprintf(folder, folder_size, "%s/%s", parent, id);
    if (is_complete(folder)) return 0;
    char partial[4200];
    snprintf(partial, sizeof partial, "%s/", parent);
    if (make_parents(partial) != 0) {
        snprintf(reason, reason_size, "cannot make %s (%s)", parent, strerror(errno));
        return -1;
    }
    snprintf(partial, sizeof partial, "%s/.%s.%ld.XXXXXX", parent, id, (long)getpid());
    if (!mkdtemp(partial)) {
        snprintf(reason, reason_size, "cannot write in %s (%s)", parent, strerror(errno));
        return -1;
    }
    int status = unpack(archive, partial, reason, reason_size);
    if (status == 0 && rename(partial, folder) != 0 && !is_complete(folder)) {
        snprintf(reason, reason_size, "cannot rename %s to %s (%s)", partial, folder, strerror(errno));
        status = -1;
    }
    nftw(partial, remove_one, 16, FTW_DEPTH | FTW_PHYS); /* left only by a failure or a concurrent winner */
    return status == 0 && is_complete(folder) ? 0 : -1;
}

int runtime_carried(const char *resource_dir) {
    char archive[4096];
    snprintf(archive, sizeof archive, "%s/runtime.zip", resource_dir ? resource_dir : "");
    return resource_dir && access(archive, R_OK) == 0;
}

int runtime_folder(const char *resource_dir, char *folder, size_t folder_size, char *reason, size_t reason_size) {
    char archive[4096], id[128], parent[4096];
    snprintf(archive, sizeof archive, "%s/runtime.zip", resource_dir);
    if (read_id(resource_dir, id, sizeof id) != 0) {
        snprintf(reason, reason_size, "%s/runtime.id is missing or not a hex digest: the FMU is damaged; build it "
                 "again", resource_dir);
        return -1;
    }
    const char *cache = getenv("AAA_COSIM_RUNTIME_CACHE"), *xdg = getenv("XDG_CACHE_HOME"), *home = getenv("HOME");
    parent[0] = '\0';
    if (cache && *cache) snprintf(parent, sizeof parent, "%s", cache);
    else if (xdg && *xdg == '/') snprintf(parent, sizeof parent, "%s/aaa-cosim/runtime", xdg);
    else if (home && *home == '/') snprintf(parent, sizeof parent, "%s/.cache/aaa-cosim/runtime", home);
    char first[1024] = "";
    if (parent[0]) {
        if (unpack_into(archive, parent, id, folder, folder_size, reason, reason_size) == 0) return 0;
        snprintf(first, sizeof first, "%s", reason);
    }
    /* no cache folder to write: beside the resources (unpacked again on each extraction) */
    snprintf(parent, sizeof parent, "%s/runtime", resource_dir);
    if (unpack_into(archive, parent, id, folder, folder_size, reason, reason_size) == 0) return 0;
    if (first[0]) {
        size_t used = strlen(reason);
        snprintf(reason + used, reason_size - used, "; and in the cache: %s. Set AAA_COSIM_RUNTIME_CACHE to a folder "
                 "this user can write (about 350 MB, once per FMU build)", first);
    }
    return -1;
}
