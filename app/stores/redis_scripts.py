"""The Redis store's Lua scripts: each runs atomically on the server and touches the keys of one session
(one hash tag, so one cluster slot) or one index. Their KEYS and ARGV are documented above each."""

# HSET of n (field, value) pairs from ARGV[at], in chunks: Lua's unpack() refuses more than ~8000 values
# (a 16M-voxel layer is 15,625 blocks).
_HSET_CHUNKS = """
local function hset_pairs(key, at, n)
    local done = 0
    while done < n do
        local m = math.min(n - done, 1000)
        local first = at + 2 * done
        redis.call('HSET', key, unpack(ARGV, first, first + 2 * m - 1))
        done = done + m
    end
end
"""

# Remember an idempotency key in a hash (KEYS[h]) and a sorted set of its keys (KEYS[z]), and forget the set's
# keys past the window or beyond the count.
_REMEMBER = """
local function remember(h, z, key, record, now_ms, window_ms, max_keys)
    redis.call('HSET', KEYS[h], key, record)
    redis.call('ZADD', KEYS[z], now_ms, key)
    local oldest = '(' .. (now_ms - window_ms)
    local stale = redis.call('ZRANGEBYSCORE', KEYS[z], '-inf', oldest, 'LIMIT', 0, 64)
    local excess = redis.call('ZCARD', KEYS[z]) - max_keys
    if excess > 0 then
        for _, k in ipairs(redis.call('ZRANGE', KEYS[z], 0, excess - 1)) do table.insert(stale, k) end
    end
    for _, k in ipairs(stale) do
        redis.call('HDEL', KEYS[h], k)
        redis.call('ZREM', KEYS[z], k)
    end
end
"""

# The record of an idempotency key (KEYS[h]; its time in the sorted set KEYS[z]), or false: none, or one older
# than the window, which is forgotten here as the memory store forgets it (`IdempotencyLog.check`).
_FRESH = """
local function fresh(h, z, key, now_ms, window_ms)
    local record = redis.call('HGET', KEYS[h], key)
    if not record then return false end
    local at = redis.call('ZSCORE', KEYS[z], key)
    if at and tonumber(at) < now_ms - window_ms then
        redis.call('HDEL', KEYS[h], key)
        redis.call('ZREM', KEYS[z], key)
        return false
    end
    return record
end
"""

# Append an event (`app.stores.events`) to the session's stream (KEYS[i]; trimmed to about ARGV[at + 2]
# entries) and publish "<its id> <its JSON>" on the events channel (ARGV[at + 3]): its JSON is ARGV[at], the
# version, ARGV[at + 1]. In the script that commits the version, so that the stream holds every version once,
# in order, and the channel carries what the stream holds (a PUBLISH touches no key: it works on a cluster,
# whose nodes all relay it).
_EVENT = """
local function event(i, at, version)
    local data = ARGV[at] .. version .. ARGV[at + 1]
    local id = redis.call('XADD', KEYS[i], 'MAXLEN', '~', ARGV[at + 2], '*', 'e', data)
    redis.call('PUBLISH', ARGV[at + 3], id .. ' ' .. data)
end
"""

# KEYS: meta, lock, lang, vis, summary, idem, idem_at, events, commits, then the hashes written.
# A commit's own id ("c:<id>", the key of a commit without a client's key) is counted in `commits`, a client's
# key in idem_at: keyless commits, however many, never push a client's key out of the bounded set.
# ARGV: [1] version read, [2] updated_at read (with the version, the name of the state read: a session
# deleted and created again under its id restarts its versions), [3] lock token ("" without the lock),
# [4] new updated_at, [5] expiry ms ("" for none), [6] idempotency key, [7] its record, [8] now ms,
# [9] window ms, [10] keys kept, [11] number of hashes written, [12]-[15] the event (`_EVENT`), then per
# hash: its number of fields, then field, value, ...
# Returns {version} when written, {-1} without the session, {-2} when another writer came first, and
# {-3, record} when the key was seen (this very commit, resent, or another request with the key).
COMMIT_SCRIPT = (
    _HSET_CHUNKS
    + _REMEMBER
    + _FRESH
    + _EVENT
    + """
local keys_of = string.sub(ARGV[6], 1, 2) == 'c:' and 9 or 7
local seen = fresh(6, keys_of, ARGV[6], tonumber(ARGV[8]), tonumber(ARGV[9]))
if seen then return {-3, seen} end
local state = redis.call('HMGET', KEYS[1], 'version', 'updated_at')
if not state[1] then return {-1} end
if state[1] ~= ARGV[1] or state[2] ~= ARGV[2] then return {-2} end
local holder = redis.call('GET', KEYS[2])
if holder and holder ~= ARGV[3] then return {-2} end
local at = 16
for k = 10, 9 + tonumber(ARGV[11]) do
    local n = tonumber(ARGV[at])
    hset_pairs(KEYS[k], at + 1, n)
    at = at + 1 + 2 * n
end
local new = tonumber(state[1]) + 1
redis.call('HSET', KEYS[1], 'version', new, 'updated_at', ARGV[4])
remember(6, keys_of, ARGV[6], ARGV[7], tonumber(ARGV[8]), tonumber(ARGV[9]), tonumber(ARGV[10]))
event(8, 12, string.format('%d', new))
if ARGV[5] ~= '' then
    for _, k in ipairs({1, 3, 4, 5, 6, 7, 8, 9}) do redis.call('PEXPIREAT', KEYS[k], ARGV[5]) end
end
return {new}
"""
)

# KEYS: meta, lang, vis, summary, idem, idem_at, events, commits.
# ARGV: [1] idempotency key ("" for none), [2] its record, [3] now ms, [4] window ms, [5] keys kept,
# [6] expiry ms ("" for none), [7] the version created, [8]-[11] its event (`_EVENT`), then for meta, lang
# and vis: the number of fields, then field, value, ...
# Returns {0} when created, {-1} when the session exists, {-3, record} when it was made under the key (it
# exists, or it was deleted and its tombstone remembers the key).
# The events stream of a deleted incarnation stays: the new one's events follow its "deleted" event.
CREATE_SCRIPT = (
    _HSET_CHUNKS
    + _REMEMBER
    + _FRESH
    + _EVENT
    + """
-- The key's record is the live session's, or a deleted one's tombstone: a retry of its creation either way.
local seen = ARGV[1] ~= '' and fresh(5, 6, ARGV[1], tonumber(ARGV[3]), tonumber(ARGV[4]))
if seen then return {-3, seen} end
if redis.call('EXISTS', KEYS[1]) == 1 then return {-1} end
redis.call('DEL', KEYS[2], KEYS[3], KEYS[4], KEYS[5], KEYS[6], KEYS[8])  -- what a deleted incarnation left
local at = 12
for k = 1, 3 do
    local n = tonumber(ARGV[at])
    if n > 0 then hset_pairs(KEYS[k], at + 1, n) end
    at = at + 1 + 2 * n
end
if ARGV[1] ~= '' then
    remember(5, 6, ARGV[1], ARGV[2], tonumber(ARGV[3]), tonumber(ARGV[4]), tonumber(ARGV[5]))
end
event(7, 8, ARGV[7])
if ARGV[6] ~= '' then
    for k = 1, 7 do redis.call('PEXPIREAT', KEYS[k], ARGV[6]) end
else
    redis.call('PERSIST', KEYS[7])
end
return {0}
"""
)

# KEYS: meta, lang, vis, summary, idem, idem_at, events, commits.
# ARGV: [1] idempotency key ("" for none), [2] its record, [3] now ms, [4] window ms, [5]-[8] the "deleted"
# event (`_EVENT`; its version is the session's last), [9] how long the events stream stays (ms).
# Returns {0} when deleted, {-1} without the session, {-3, record} when the key was seen.
DELETE_SCRIPT = (
    _FRESH
    + _EVENT
    + """
if ARGV[1] ~= '' then
    local seen = fresh(5, 6, ARGV[1], tonumber(ARGV[3]), tonumber(ARGV[4]))
    if seen then return {-3, seen} end
end
local version = redis.call('HGET', KEYS[1], 'version')
if not version then return {-1} end
event(7, 5, version)
redis.call('PEXPIRE', KEYS[7], ARGV[9])
-- The tombstone, for the window: the session's client keys (a retry of its creation or of an update finds
-- them) and this delete's; its commit ids go.
for _, k in ipairs(redis.call('ZRANGE', KEYS[8], 0, -1)) do redis.call('HDEL', KEYS[5], k) end
redis.call('DEL', KEYS[1], KEYS[2], KEYS[3], KEYS[4], KEYS[8])
if ARGV[1] ~= '' then
    redis.call('HSET', KEYS[5], ARGV[1], ARGV[2])
    redis.call('ZADD', KEYS[6], ARGV[3], ARGV[1])
end
redis.call('PEXPIRE', KEYS[5], ARGV[4])
redis.call('PEXPIRE', KEYS[6], ARGV[4])
return {0}
"""
)

# KEYS: meta, events, idem, idem_at. ARGV: [1]-[4] the event (`_EVENT`) of the session's current version,
# [5] an idempotency key ("" for none; an announcement remembers none, but refuses one an update used),
# [6] now ms, [7] window ms.
# Returns {1} when published, {0} without the session, {-3, record} when the key was seen (nothing published).
ANNOUNCE_SCRIPT = (
    _FRESH
    + _EVENT
    + """
local version = redis.call('HGET', KEYS[1], 'version')
if not version then return {0} end
local seen = ARGV[5] ~= '' and fresh(3, 4, ARGV[5], tonumber(ARGV[6]), tonumber(ARGV[7]))
if seen then return {-3, seen} end
event(2, 1, version)
local ttl = redis.call('PTTL', KEYS[1])
if ttl > 0 then redis.call('PEXPIRE', KEYS[2], ttl) end
return {1}
"""
)

# KEYS: the session's recording (a list), its meta. ARGV: [1] the packed frame, [2] the frames kept.
# Appends while the session exists, thins past the limit as `app.stores.recording.thin` does (a dropped
# frame is set to '' and all of them removed at once; a kept one of the halved level is rewritten one level
# up), and gives the list the session's expiry. Returns 1 when appended, 0 without the session.
RECORD_SCRIPT = """
if redis.call('EXISTS', KEYS[2]) == 0 then return 0 end
local n = redis.call('RPUSH', KEYS[1], ARGV[1])
local limit = tonumber(ARGV[2])
local function level(frame)
    local marker = string.byte(frame, 1) or 107
    if marker == 115 then return 0 end  -- 's'
    if marker > 128 then return marker - 128 end
    return nil
end
if n > limit then
    local frames = redis.call('LRANGE', KEYS[1], 1, n - 2)
    local counts, present = {}, 0
    for _, frame in ipairs(frames) do
        local lv = level(frame)
        if lv ~= nil then
            if counts[lv] == nil then counts[lv], present = 0, present + 1 end
            counts[lv] = counts[lv] + 1
        end
    end
    local share = math.max(2, math.floor(limit / (present + 1)))
    local halved, highest = nil, nil
    for lv, count in pairs(counts) do
        if count > share and (halved == nil or lv < halved) then halved = lv end
        if count >= 2 and (highest == nil or lv > highest) then highest = lv end
    end
    if halved == nil then halved = highest end
    if halved ~= nil then
        local drop = false
        for i, frame in ipairs(frames) do
            if level(frame) == halved then
                if drop then
                    redis.call('LSET', KEYS[1], i, '')
                else
                    redis.call('LSET', KEYS[1], i, string.char(128 + halved + 1) .. string.sub(frame, 2))
                end
                drop = not drop
            end
        end
        redis.call('LREM', KEYS[1], 0, '')
    end
    redis.call('LTRIM', KEYS[1], -2 * limit, -1)
end
local ttl = redis.call('PTTL', KEYS[2])
if ttl > 0 then redis.call('PEXPIRE', KEYS[1], ttl) end
return 1
"""

# KEYS: a robot's index. ARGV: [1] session id, [2] the score from which an entry counts as live, [3] the
# reservation's score, [4] the robot's limit. Returns 1 when reserved (or already there), 0 at the limit.
RESERVE_SCRIPT = """
if redis.call('ZSCORE', KEYS[1], ARGV[1]) then return 1 end
if redis.call('ZCOUNT', KEYS[1], ARGV[2], '+inf') >= tonumber(ARGV[4]) then return 0 end
redis.call('ZADD', KEYS[1], ARGV[3], ARGV[1])
return 1
"""

RELEASE_SCRIPT = """
if redis.call('get', KEYS[1]) == ARGV[1] then
    return redis.call('del', KEYS[1])
end
return 0
"""

RENEW_SCRIPT = """
if redis.call('get', KEYS[1]) == ARGV[1] then
    return redis.call('pexpire', KEYS[1], ARGV[2])
end
return 0
"""
