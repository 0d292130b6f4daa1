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

# Remember an idempotency key (KEYS[i], KEYS[i + 1]: the idem hash and its sorted set) and forget those
# past the window or beyond the count.
_REMEMBER = """
local function remember(i, key, record, now_ms, window_ms, max_keys)
    redis.call('HSET', KEYS[i], key, record)
    redis.call('ZADD', KEYS[i + 1], now_ms, key)
    local oldest = '(' .. (now_ms - window_ms)
    local stale = redis.call('ZRANGEBYSCORE', KEYS[i + 1], '-inf', oldest, 'LIMIT', 0, 64)
    local excess = redis.call('ZCARD', KEYS[i + 1]) - max_keys
    if excess > 0 then
        for _, k in ipairs(redis.call('ZRANGE', KEYS[i + 1], 0, excess - 1)) do table.insert(stale, k) end
    end
    for _, k in ipairs(stale) do
        redis.call('HDEL', KEYS[i], k)
        redis.call('ZREM', KEYS[i + 1], k)
    end
end
"""

# KEYS: meta, lock, lang, vis, summary, idem, idem_at, then the hashes written.
# ARGV: [1] version read, [2] updated_at read (with the version, the name of the state read: a session
# deleted and created again under its id restarts its versions), [3] lock token ("" without the lock),
# [4] new updated_at, [5] expiry ms ("" for none), [6] idempotency key, [7] its record, [8] now ms,
# [9] window ms, [10] keys kept, [11] number of hashes written, then per hash: its number of fields, then
# field, value, ...
# Returns {version} when written, {-1} without the session, {-2} when another writer came first, and
# {-3, record} when the key was seen (this very commit, resent, or another request with the key).
COMMIT_SCRIPT = (
    _HSET_CHUNKS
    + _REMEMBER
    + """
local seen = redis.call('HGET', KEYS[6], ARGV[6])
if seen then return {-3, seen} end
local state = redis.call('HMGET', KEYS[1], 'version', 'updated_at')
if not state[1] then return {-1} end
if state[1] ~= ARGV[1] or state[2] ~= ARGV[2] then return {-2} end
local holder = redis.call('GET', KEYS[2])
if holder and holder ~= ARGV[3] then return {-2} end
local at = 12
for k = 8, 7 + tonumber(ARGV[11]) do
    local n = tonumber(ARGV[at])
    hset_pairs(KEYS[k], at + 1, n)
    at = at + 1 + 2 * n
end
local new = tonumber(state[1]) + 1
redis.call('HSET', KEYS[1], 'version', new, 'updated_at', ARGV[4])
remember(6, ARGV[6], ARGV[7], tonumber(ARGV[8]), tonumber(ARGV[9]), tonumber(ARGV[10]))
if ARGV[5] ~= '' then
    for _, k in ipairs({1, 3, 4, 5, 6, 7}) do redis.call('PEXPIREAT', KEYS[k], ARGV[5]) end
end
return {new}
"""
)

# KEYS: meta, lang, vis, summary, idem, idem_at.
# ARGV: [1] idempotency key ("" for none), [2] its record, [3] now ms, [4] window ms, [5] keys kept,
# [6] expiry ms ("" for none), then for meta, lang and vis: the number of fields, then field, value, ...
# Returns {0} when created, {-1} when the session exists, {-3, record} when it exists made under the key.
CREATE_SCRIPT = (
    _HSET_CHUNKS
    + _REMEMBER
    + """
if redis.call('EXISTS', KEYS[1]) == 1 then
    local seen = ARGV[1] ~= '' and redis.call('HGET', KEYS[5], ARGV[1])
    if seen then return {-3, seen} end
    return {-1}
end
redis.call('DEL', KEYS[2], KEYS[3], KEYS[4], KEYS[5], KEYS[6])  -- what a deleted incarnation left
local at = 7
for k = 1, 3 do
    local n = tonumber(ARGV[at])
    if n > 0 then hset_pairs(KEYS[k], at + 1, n) end
    at = at + 1 + 2 * n
end
if ARGV[1] ~= '' then
    remember(5, ARGV[1], ARGV[2], tonumber(ARGV[3]), tonumber(ARGV[4]), tonumber(ARGV[5]))
end
if ARGV[6] ~= '' then
    for k = 1, 6 do redis.call('PEXPIREAT', KEYS[k], ARGV[6]) end
end
return {0}
"""
)

# KEYS: meta, lang, vis, summary, idem, idem_at.
# ARGV: [1] idempotency key ("" for none), [2] its record, [3] now ms, [4] window ms.
# Returns {0} when deleted, {-1} without the session, {-3, record} when the key was seen.
DELETE_SCRIPT = """
if ARGV[1] ~= '' then
    local seen = redis.call('HGET', KEYS[5], ARGV[1])
    if seen then return {-3, seen} end
end
if redis.call('EXISTS', KEYS[1]) == 0 then return {-1} end
redis.call('DEL', KEYS[1], KEYS[2], KEYS[3], KEYS[4], KEYS[5], KEYS[6])
if ARGV[1] ~= '' then  -- the tombstone: this delete's record, for the window
    redis.call('HSET', KEYS[5], ARGV[1], ARGV[2])
    redis.call('ZADD', KEYS[6], ARGV[3], ARGV[1])
    redis.call('PEXPIRE', KEYS[5], ARGV[4])
    redis.call('PEXPIRE', KEYS[6], ARGV[4])
end
return {0}
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
