-- Wireshark dissector for the VM-110 UDP EG-Link (TS-0006), following shared/spec/interpretation.md.
--
-- One file on purpose: Wireshark 4.4 loads every .lua in a plugin folder as a plugin.
-- Runs unchanged on Lua 5.2 (Wireshark 4.0) and Lua 5.4 (Wireshark 4.4): no bit32, no 5.3
-- operators; bit operations come from the `bit` library (LuaBitOp) that Wireshark ships with both.
--
-- Layout of this file, top to bottom:
--   1. protocol constants (the values and display names of vm110/constants.py)
--   2. CRC engine
--   3. decode(): UDP payload bytes -> a plain record (no Wireshark objects), the rules of
--      vm110/decode.py; a later analysis layer works on these records
--   4. fields, experts, preferences
--   5. tree and Info column built from a record
--   6. dissector, heuristic and port registration

local PLUGIN_VERSION = "0.1.0"
if set_plugin_info then
    set_plugin_info({
        version = PLUGIN_VERSION,
        description = "VM-110 EG-Link (TS-0006) dissector",
        repository = "vm110 project: dissector/vm110.lua",
    })
end

-- Every tree item is a userdata (TvbRange, TreeItem) that the collector must finalise: most of
-- this dissector's cost. Measured in `make bench`: on Lua 5.4 (Wireshark 4.4) the generational
-- collector takes about 40% less CPU; on Lua 5.2 (Wireshark 4.0) collecting continuously
-- (pause 100) with larger steps about 20% less (a small heap stays in the CPU cache).
-- These settings apply to Wireshark's whole Lua state (every Lua plugin).
if _VERSION == "Lua 5.4" then
    collectgarbage("generational")
else
    collectgarbage("setpause", 100)
    collectgarbage("setstepmul", 800)
end

local byte, sub, fmt, concat = string.byte, string.sub, string.format, table.concat
local floor = math.floor

---------------------------------------------------------------------------------------------
-- 1. Protocol constants
---------------------------------------------------------------------------------------------
local ID_LEN, HEADER_LEN, CRC_LEN = 4, 12, 4
local PREFIX_LEN = ID_LEN + HEADER_LEN
local OVERHEAD = PREFIX_LEN + CRC_LEN
local MAX_PAYLOAD = 492
local SUPPORTED_REVISION = 0
local VRPO_MAX_DATA = 488
local DEFAULT_INPUT_PORT, OUTPUT_PORT_OFFSET = 5825, 2
-- Timing and numbering of section 5.1 (interpretation.md "Timing", "Serial numbers", "VRPO split").
local VRPI_WATCHDOG_MS, VRPO_WATCHDOG_MS, VRPO_PERIOD_MIN_MS, VRPO_PERIOD_MAX_MS = 500, 2000, 50, 200
local COMMAND_RESEND_MS, VRCI_FAIL_MS, VRCO_GIVE_UP_MS, VRPO_BURST_GAP_MS = 100, 2000, 2000, 20
local SERIAL_MODULUS, SERIAL_HALF, VRPO_HEADER_SIZE = 65536, 32768, 2
local ACK_OF = { VRAO = "VRCI", VRAI = "VRCO" }
local ES_RELAYS_CLOSED_FROM = 0x10

local BU_STATE = {
    [0x00] = "Initial", [0x01] = "Stopped", [0x02] = "External link error", [0x03] = "Blocked",
    [0x04] = "Failed", [0x10] = "Disarmed", [0x11] = "Armed",
}
local LINK_STATUS = {
    [0] = "Unused", [1] = "Operational", [2] = "No link", [3] = "Link error",
    [4] = "Interface error", [5] = "Data error", [6] = "Passive",
}
local RU_STATE = { [0] = "Initial", [1] = "Disarmed", [2] = "Armed", [3] = "Enabled", [4] = "Stopped" }
local RU_DISABLED = { [0] = "Enabled", [1] = "Disabled (tilt)", [2] = "Disabled (inactivity)" }
local RU_CABLE = { [0] = "Wireless", [1] = "Cable" }
local RU_DOCKED = { [0] = "Not docked", [1] = "Docked" }
local ENCODER_SWITCH = { [0] = "Released", [1] = "Pushed" }
local CRC_STATUS = { [0] = "Bad", [1] = "Good", [2] = "Unverified" }
local CRC_BAD, CRC_GOOD, CRC_UNVERIFIED = 0, 1, 2

-- Payload layouts: {name, width, kind, names}; kind "u" unsigned LE, "s" signed LE, "b" bytes.
local VRPI_LAYOUT = {
    { "bu_state", 1, "u", BU_STATE }, { "vlaps", 1, "u" }, { "unarmed_rus", 1, "u" },
    { "eg_link", 1, "u", LINK_STATUS }, { "ec_link", 1, "u", LINK_STATUS },
    { "c_link", 1, "u", LINK_STATUS }, { "armed_ru", 2, "u" },
    { "ru_state", 1, "u", RU_STATE }, { "ru_battery", 1, "u" }, { "ru_rssi", 1, "u" },
    { "ru_cable", 1, "u", RU_CABLE }, { "ru_docked", 1, "u", RU_DOCKED },
    { "ru_disabled", 1, "u", RU_DISABLED },
    { "joystick1", 2, "s" }, { "joystick2", 2, "s" }, { "joystick3", 2, "s" }, { "joystick4", 2, "s" },
    { "switch1", 2, "s" }, { "switch2", 2, "s" }, { "switch3", 2, "s" }, { "switch4", 2, "s" },
    { "switch5", 2, "s" }, { "switch6", 2, "s" }, { "switch7", 2, "s" }, { "switch8", 2, "s" },
    { "encoder", 1, "u" }, { "encoder_switch", 1, "u", ENCODER_SWITCH }, { "vrpi_spare", 6, "b" },
}
local COMMAND_LAYOUT = { { "command_id", 2, "u" }, { "command_spare", 4, "u" }, { "command_data", 16, "b" } }
local ACK_LAYOUT = { { "command_id", 2, "u" } }
-- periodic_data (the rest, up to 488 bytes) follows the packet number.
local VRPO_LAYOUT = { { "packet_number", 2, "u" } }

local function layout_size(layout)
    local size = 0
    for _, f in ipairs(layout) do size = size + f[2] end
    return size
end

-- Packet types by ID. min/max: payload sizes; the 4th ID character gives the direction.
local TYPES = {}
for _, t in ipairs({
    { "VRPI", "VisionRemote Periodic Input", VRPI_LAYOUT },
    { "VRPO", "VisionRemote Periodic Output", VRPO_LAYOUT, VRPO_MAX_DATA },
    { "VRCI", "VisionRemote Command Input", COMMAND_LAYOUT },
    { "VRCO", "VisionRemote Command Output", COMMAND_LAYOUT },
    { "VRAI", "VisionRemote Acknowledge Input", ACK_LAYOUT },
    { "VRAO", "VisionRemote Acknowledge Output", ACK_LAYOUT },
}) do
    local min = layout_size(t[3])
    TYPES[t[1]] = {
        id = t[1], description = t[2], layout = t[3], min = min, max = min + (t[4] or 0),
        direction = sub(t[1], 4, 4) == "I" and "Input" or "Output",
    }
end

-- Documented ranges (warnings): VRPI fields only.
local RANGES = { vlaps = { 0, 3 }, ru_battery = { 0, 100 }, ru_rssi = { 0, 100 } }
for i = 1, 4 do RANGES["joystick" .. i] = { -1000, 1000 } end
for i = 1, 8 do RANGES["switch" .. i] = { -1, 1000 } end
-- Fields that must be zero while armed_ru is 0 (TS-0006 4.1).
local RU_FIELDS = { ru_state = true, ru_battery = true, ru_rssi = true, ru_cable = true,
    ru_docked = true, ru_disabled = true, encoder = true, encoder_switch = true }
for i = 1, 4 do RU_FIELDS["joystick" .. i] = true end
for i = 1, 8 do RU_FIELDS["switch" .. i] = true end

---------------------------------------------------------------------------------------------
-- 2. CRC engine
-- Slicing by 4 with the `bit` library (LuaBitOp, which Wireshark ships with Lua 5.2 and 5.4
-- alike): per 4 bytes one string.byte call, two bit calls and four lookups in 256-entry
-- tables that stay in the CPU cache. (A 64K-entry XOR table with no calls at all measured
-- slower inside tshark: the lookups miss the cache.) Registers are LuaBitOp's signed 32 bits.
---------------------------------------------------------------------------------------------
local bit = bit or require("bit")
local bxor, band, lshift, rshift = bit.bxor, bit.band, bit.lshift, bit.rshift
local TWO32 = 4294967296

-- The register after 8 zero bits, bit by bit: builds the tables only.
local function shift8(r, reflected)
    for _ = 1, 8 do
        if reflected then
            local low = band(r, 1)
            r = rshift(r, 1)
            if low ~= 0 then r = bxor(r, 0xEDB88320) end
        else
            local high = band(r, 0x80000000)
            r = lshift(r, 1)
            if high ~= 0 then r = bxor(r, 0x04C11DB7) end
        end
    end
    return r
end

-- T8[v]: the register after one byte, from v in the byte consumed next. Wk[v]: the register
-- after four zero bytes, from v in byte k of the register (k = 1 the low byte). By linearity
-- the register after four bytes is W1[x0] ^ W2[x1] ^ W3[x2] ^ W4[x3], x = register ^ word.
local function build_engine(reflected)
    local T8, W = {}, { {}, {}, {}, {} }
    for v = 0, 255 do
        T8[v] = shift8(reflected and v or lshift(v, 24), reflected)
        for k = 1, 4 do
            local r = lshift(v, 8 * (k - 1))
            for _ = 1, 4 do r = shift8(r, reflected) end
            W[k][v] = r
        end
    end
    return { reflected = reflected, T8 = T8, W1 = W[1], W2 = W[2], W3 = W[3], W4 = W[4] }
end

local ENGINES = { [false] = build_engine(false), [true] = build_engine(true) }

-- CRC variants of interpretation.md: all with init 0xFFFFFFFF and polynomial 0x04C11DB7.
local CRC_VARIANTS = {
    { name = "mpeg2", label = "CRC-32/MPEG-2 (default)", reflected = false, xorout = false },
    { name = "iso-hdlc", label = "CRC-32/ISO-HDLC (zlib)", reflected = true, xorout = true },
    { name = "bzip2", label = "CRC-32/BZIP2", reflected = false, xorout = true },
    { name = "jamcrc", label = "CRC-32/JAMCRC", reflected = true, xorout = false },
}

-- CRC of the first len bytes of s, as an unsigned number.
local function crc_of(s, len, variant)
    local e = ENGINES[variant.reflected]
    local W1, W2, W3, W4, T8 = e.W1, e.W2, e.W3, e.W4, e.T8
    local r, i, words = -1, 1, len - len % 4
    if e.reflected then
        while i <= words do
            local a, b, c, d = byte(s, i, i + 3)
            local x = bxor(r, ((d * 256 + c) * 256 + b) * 256 + a)
            if x < 0 then x = x + TWO32 end
            local x0 = x % 256
            x = (x - x0) / 256
            local x1 = x % 256
            x = (x - x1) / 256
            local x2 = x % 256
            r = bxor(W1[x0], W2[x1], W3[x2], W4[(x - x2) / 256])
            i = i + 4
        end
        for j = i, len do r = bxor(rshift(r, 8), T8[bxor(band(r, 255), byte(s, j))]) end
    else
        while i <= words do
            local a, b, c, d = byte(s, i, i + 3)
            local x = bxor(r, ((a * 256 + b) * 256 + c) * 256 + d)
            if x < 0 then x = x + TWO32 end
            local x0 = x % 256
            x = (x - x0) / 256
            local x1 = x % 256
            x = (x - x1) / 256
            local x2 = x % 256
            r = bxor(W1[x0], W2[x1], W3[x2], W4[(x - x2) / 256])
            i = i + 4
        end
        for j = i, len do r = bxor(lshift(r, 8), T8[bxor(rshift(r, 24), byte(s, j))]) end
    end
    if r < 0 then r = r + TWO32 end
    if variant.xorout then r = TWO32 - 1 - r end
    return r
end

---------------------------------------------------------------------------------------------
-- 3. decode(): the rules of vm110/decode.py, on a Lua string
-- Record (false = absent): n, type, info (TYPES entry), header values (revision ... spare),
-- crc_off (offset of the CRC), crc, crc_calc, crc_status, pay_end (end of the payload span),
-- payload (true when the payload is decoded), values (payload field -> value), present
-- (layout entries decoded), decoded_end, data_len (VRPO periodic data), es_relays_open,
-- problems (code -> true), fieldwarn (field -> list of codes), extra (extra_payload).
---------------------------------------------------------------------------------------------
local function u16(s, o)
    local lo, hi = byte(s, o + 1, o + 2)
    return lo + hi * 256
end
local function u32(s, o)
    local a, b, c, d = byte(s, o + 1, o + 4)
    return ((d * 256 + c) * 256 + b) * 256 + a
end
local function s16(v) if v >= 0x8000 then return v - 0x10000 end return v end

-- A reader per layout for whole payloads: one string.byte call into locals and one table
-- constructor, no loop. Generated from the layout, so that the layout stays the only
-- description of each packet.
local function compile_reader(layout)
    local parts, locals, off = {}, {}, PREFIX_LEN
    for _, f in ipairs(layout) do
        local name, width, kind, expr = f[1], f[2], f[3], nil
        if kind == "b" then
            expr = fmt("sub(s, %d, %d)", off + 1, off + width)
        elseif width == 1 then
            expr = fmt("b%d", off + 1)
        elseif width == 2 then
            expr = fmt(kind == "s" and "s16(b%d + b%d * 256)" or "b%d + b%d * 256", off + 1, off + 2)
        else
            expr = fmt("((b%d * 256 + b%d) * 256 + b%d) * 256 + b%d", off + 4, off + 3, off + 2, off + 1)
        end
        parts[#parts + 1] = name .. " = " .. expr
        off = off + width
    end
    for i = PREFIX_LEN + 1, off do locals[#locals + 1] = "b" .. i end
    local code = fmt("local byte, sub, s16 = ...\nreturn function(s)\nlocal %s = byte(s, %d, %d)\n"
        .. "return { %s }\nend", concat(locals, ", "), PREFIX_LEN + 1, off, concat(parts, ", "))
    return assert(load(code, "=vm110 reader", "t", {}))(byte, sub, s16)
end

local HEADER = { { "revision", 4, 2 }, { "origin", 6, 2 }, { "serial", 8, 2 }, { "size", 10, 2 }, { "spare", 12, 4 } }

-- VRPI value checks, one entry per field: {name, value names, low, high, is an RU field}.
local VRPI_CHECKS = {}
for _, f in ipairs(VRPI_LAYOUT) do
    local range = RANGES[f[1]]
    VRPI_CHECKS[#VRPI_CHECKS + 1] = { f[1], f[4] or false, range and range[1] or false,
        range and range[2] or false, RU_FIELDS[f[1]] or false }
end

local function warn(r, field, code)
    local list = r.fieldwarn[field]
    if not list then
        list = {}
        r.fieldwarn[field] = list
    end
    list[#list + 1] = code
end

local function check_values(r, info)
    local v = r.values
    if v.vrpi_spare and v.vrpi_spare:find("[^\0]") then warn(r, "vrpi_spare", "spare_nonzero") end
    if v.command_spare and v.command_spare ~= 0 then warn(r, "command_spare", "spare_nonzero") end
    if info.id ~= "VRPI" then return end
    local disarmed = v.armed_ru == 0
    for i = 1, #VRPI_CHECKS do
        local c = VRPI_CHECKS[i]
        local name = c[1]
        local value = v[name]
        if value ~= nil then
            if c[2] and c[2][value] == nil then warn(r, name, "unknown_enum") end
            if c[3] and (value < c[3] or value > c[4]) then warn(r, name, "out_of_range") end
            if disarmed and c[5] and value ~= 0 then warn(r, name, "disarmed_ru_data") end
        end
    end
end

-- The fields that fit whole in a payload cut short.
local function read_partial(s, layout, limit)
    local v, present, off = {}, {}, PREFIX_LEN
    for _, f in ipairs(layout) do
        local width, kind = f[2], f[3]
        if off + width > limit then break end
        local value
        if kind == "b" then
            value = sub(s, off + 1, off + width)
        elseif width == 1 then
            value = byte(s, off + 1)
        elseif width == 2 then
            value = u16(s, off)
            if kind == "s" then value = s16(value) end
        else
            value = u32(s, off)
        end
        v[f[1]] = value
        present[#present + 1] = f
        off = off + width
    end
    return v, present, off
end

local function decode_payload(r, s, info)
    local limit = r.pay_end
    local v
    if limit - PREFIX_LEN >= info.min then
        v = info.read(s)
        r.present, r.decoded_end = info.layout, PREFIX_LEN + info.min
    else
        r.problems.truncated = true
        v, r.present, r.decoded_end = read_partial(s, info.layout, limit)
    end
    r.values = v
    if info.id == "VRPO" and v.packet_number then
        local off = r.decoded_end
        local len = limit - off
        if len > VRPO_MAX_DATA then len = VRPO_MAX_DATA end
        r.data_len = len
        v.periodic_data = sub(s, off + 1, off + len)
        r.decoded_end = off + len
    elseif info.id == "VRPI" and v.bu_state then
        r.es_relays_open = v.bu_state < ES_RELAYS_CLOSED_FROM
    end
end

-- Each type gets its reader; layout entries get their offset in the packet (for the tree).
for _, info in pairs(TYPES) do
    info.read = compile_reader(info.layout)
    local off = PREFIX_LEN
    for _, f in ipairs(info.layout) do
        f.off = off
        off = off + f[2]
    end
end

local NO_VALUES = {} -- values of a packet whose payload is not decoded: shared, never written

-- s: the UDP payload; variant: a CRC_VARIANTS entry, or nil when validation is off;
-- big_endian: stored CRC byte order; known_crc: the calculated CRC when memoised.
local function decode(s, variant, big_endian, known_crc)
    local n = #s
    local problems = {}
    -- Every key up front (false = absent): one allocation instead of a rehash per new key.
    local r = { n = n, problems = problems, fieldwarn = {}, values = NO_VALUES, type = false, info = false,
        revision = false, origin = false, serial = false, size = false, spare = false, crc_off = false,
        pay_end = false, crc = false, crc_calc = false, crc_status = false, payload = false, present = false,
        decoded_end = false, data_len = false, extra = false, es_relays_open = false, info_text = false }
    local info
    if n >= ID_LEN then
        r.type = sub(s, 1, ID_LEN)
        info = TYPES[r.type]
        r.info = info
        if not info then problems.unknown_id = true end
    end
    if n < PREFIX_LEN then
        for _, h in ipairs(HEADER) do
            if h[2] + h[3] > n then break end
            r[h[1]] = h[3] == 2 and u16(s, h[2]) or u32(s, h[2])
        end
        problems.truncated = true
        return r
    end
    local r1, r2, o1, o2, s1, s2, z1, z2, p1, p2, p3, p4 = byte(s, 5, PREFIX_LEN)
    local revision, origin, size = r1 + r2 * 256, o1 + o2 * 256, z1 + z2 * 256
    local spare = ((p4 * 256 + p3) * 256 + p2) * 256 + p1
    r.revision, r.origin, r.serial, r.size, r.spare = revision, origin, s1 + s2 * 256, size, spare
    if n >= OVERHEAD then
        local off = PREFIX_LEN + size
        if off > n - CRC_LEN then off = n - CRC_LEN end
        r.crc_off, r.pay_end = off, off
        if big_endian then
            local a, b, c, d = byte(s, off + 1, off + 4)
            r.crc = ((a * 256 + b) * 256 + c) * 256 + d
        else
            r.crc = u32(s, off)
        end
        if variant then
            local calc = known_crc or crc_of(s, off, variant)
            r.crc_calc = calc
            if calc == r.crc then
                r.crc_status = CRC_GOOD
            else
                r.crc_status = CRC_BAD
                problems.bad_crc = true
            end
        else
            r.crc_status = CRC_UNVERIFIED
        end
    end
    if revision ~= SUPPORTED_REVISION then problems.revision = true end
    if n ~= OVERHEAD + size then problems.size_mismatch = true end
    if size > MAX_PAYLOAD then problems.size_too_large = true end
    if spare ~= 0 then warn(r, "spare", "spare_nonzero") end
    if origin ~= 0 and info and info.direction == "Output" then warn(r, "origin", "origin_nonzero") end
    if n < OVERHEAD then
        problems.truncated = true -- no room for a CRC: nothing after the header
        return r
    end
    if not info or revision ~= SUPPORTED_REVISION then return r end -- header only

    r.payload = true
    decode_payload(r, s, info)
    r.extra = r.pay_end - PREFIX_LEN > info.max
    check_values(r, info)
    return r
end

---------------------------------------------------------------------------------------------
-- 4. Protocol, fields, experts, preferences
---------------------------------------------------------------------------------------------
local vm110 = Proto("vm110", "VM-110 EG-Link")

local F = {
    type = ProtoField.string("vm110.type", "Packet ID"),
    direction = ProtoField.string("vm110.direction", "Direction"),
    revision = ProtoField.uint16("vm110.revision", "Revision", base.DEC),
    origin = ProtoField.uint16("vm110.origin", "Origin", base.HEX),
    serial = ProtoField.uint16("vm110.serial", "Serial", base.DEC),
    size = ProtoField.uint16("vm110.size", "Payload size", base.DEC),
    spare = ProtoField.uint32("vm110.spare", "Spare", base.HEX),
    crc = ProtoField.uint32("vm110.crc", "CRC", base.HEX),
    crc_calculated = ProtoField.uint32("vm110.crc.calculated", "Calculated CRC", base.HEX),
    crc_status = ProtoField.uint8("vm110.crc.status", "CRC status", base.DEC, CRC_STATUS),
    undecoded = ProtoField.bytes("vm110.undecoded", "Undecoded bytes"),
    -- VRPI
    bu_state = ProtoField.uint8("vm110.bu_state", "BU state", base.HEX, BU_STATE),
    es_relays_open = ProtoField.bool("vm110.es_relays_open", "ES-Link relays open"),
    vlaps = ProtoField.uint8("vm110.vlaps", "VLAPs", base.DEC),
    unarmed_rus = ProtoField.uint8("vm110.unarmed_rus", "Unarmed RUs", base.DEC),
    eg_link = ProtoField.uint8("vm110.eg_link", "EG-Link status", base.HEX, LINK_STATUS),
    ec_link = ProtoField.uint8("vm110.ec_link", "EC-Link status", base.HEX, LINK_STATUS),
    c_link = ProtoField.uint8("vm110.c_link", "C-Link status", base.HEX, LINK_STATUS),
    armed_ru = ProtoField.uint16("vm110.armed_ru", "Armed RU", base.HEX),
    ru_state = ProtoField.uint8("vm110.ru_state", "RU state", base.HEX, RU_STATE),
    ru_battery = ProtoField.uint8("vm110.ru_battery", "RU battery (%)", base.DEC),
    ru_rssi = ProtoField.uint8("vm110.ru_rssi", "RU C-Link RSSI (%)", base.DEC),
    ru_cable = ProtoField.uint8("vm110.ru_cable", "RU cable", base.HEX, RU_CABLE),
    ru_docked = ProtoField.uint8("vm110.ru_docked", "RU docked", base.HEX, RU_DOCKED),
    ru_disabled = ProtoField.uint8("vm110.ru_disabled", "RU disabled", base.HEX, RU_DISABLED),
    encoder = ProtoField.uint8("vm110.encoder", "Encoder value", base.DEC),
    encoder_switch = ProtoField.uint8("vm110.encoder_switch", "Encoder switch", base.HEX, ENCODER_SWITCH),
    vrpi_spare = ProtoField.bytes("vm110.vrpi_spare", "Spare"),
    -- VRPO
    packet_number = ProtoField.uint16("vm110.packet_number", "Packet number", base.DEC),
    periodic_data = ProtoField.bytes("vm110.periodic_data", "Periodic data"),
    -- VRCI / VRCO / VRAI / VRAO: one command_id field, so a filter shows a command with its acks
    command_id = ProtoField.uint16("vm110.command_id", "Command ID", base.DEC),
    command_spare = ProtoField.uint32("vm110.command_spare", "Spare", base.HEX),
    command_data = ProtoField.bytes("vm110.command_data", "Command data"),
}
for i = 1, 4 do F["joystick" .. i] = ProtoField.int16("vm110.joystick" .. i, "Joystick " .. i, base.DEC) end
for i = 1, 8 do F["switch" .. i] = ProtoField.int16("vm110.switch" .. i, "Switch " .. i, base.DEC) end
-- Stream analysis (section 7): generated fields, all computed from earlier frames of the capture.
local frametypes = frametype or {} -- framenum types (arrows in the GUI) where this Wireshark has them
F.serial_missing = ProtoField.uint32("vm110.analysis.serial_missing", "Packets missing before this one", base.DEC)
F.serial_duplicate = ProtoField.uint8("vm110.analysis.serial_duplicate", "Duplicate serial", base.DEC)
F.serial_out_of_order = ProtoField.uint8("vm110.analysis.serial_out_of_order", "Out-of-order (late) serial", base.DEC)
F.interval = ProtoField.double("vm110.analysis.interval", "Interval since the previous packet of this type (ms)")
F.retransmission_of = ProtoField.framenum("vm110.analysis.retransmission_of", "Retransmission of frame",
    base.NONE, frametypes.RETRANS_PREV)
F.retransmission_number = ProtoField.uint16("vm110.analysis.retransmission_number", "Retransmission number", base.DEC)
F.since_first = ProtoField.double("vm110.analysis.since_first", "Time since the first transmission (ms)")
F.resend_interval = ProtoField.double("vm110.analysis.resend_interval", "Time since the previous transmission (ms)")
F.ack_in = ProtoField.framenum("vm110.analysis.ack_in", "Acknowledged in frame", base.NONE, frametypes.ACK)
F.ack_to = ProtoField.framenum("vm110.analysis.ack_to", "Acknowledges the command of frame", base.NONE,
    frametypes.REQUEST)
F.ack_time = ProtoField.double("vm110.analysis.ack_time", "Acknowledged after, from the first transmission (ms)")
F.ack_time_last = ProtoField.double("vm110.analysis.ack_time_last", "Acknowledged after, from the last transmission (ms)")
F.burst_packets = ProtoField.uint16("vm110.burst.packets", "VRPO packets in the burst", base.DEC)
F.burst_size = ProtoField.uint32("vm110.burst.size", "Periodic data in the burst (bytes)", base.DEC)
F.burst_frame = ProtoField.framenum("vm110.burst.frame", "VRPO packet in frame")
F.reassembled = ProtoField.bytes("vm110.reassembled", "Reassembled periodic data")
local field_list = {}
for _, f in pairs(F) do field_list[#field_list + 1] = f end
vm110.fields = field_list

-- One expert per problem and warning code of vm110.decode(): abbrev "vm110.expert.<code>".
local group, severity = expert.group, expert.severity
local E = {
    unknown_id = ProtoExpert.new("vm110.expert.unknown_id", "Unknown packet ID", group.PROTOCOL, severity.ERROR),
    bad_crc = ProtoExpert.new("vm110.expert.bad_crc", "Bad CRC", group.CHECKSUM, severity.ERROR),
    revision = ProtoExpert.new("vm110.expert.revision", "Unsupported revision", group.PROTOCOL, severity.ERROR),
    size_mismatch = ProtoExpert.new("vm110.expert.size_mismatch", "Size does not match the UDP length",
        group.MALFORMED, severity.ERROR),
    size_too_large = ProtoExpert.new("vm110.expert.size_too_large", "Size above 492", group.MALFORMED, severity.ERROR),
    truncated = ProtoExpert.new("vm110.expert.truncated", "Truncated", group.MALFORMED, severity.ERROR),
    spare_nonzero = ProtoExpert.new("vm110.expert.spare_nonzero", "Spare not zero", group.PROTOCOL, severity.WARN),
    origin_nonzero = ProtoExpert.new("vm110.expert.origin_nonzero", "Origin not zero on an output packet",
        group.PROTOCOL, severity.WARN),
    out_of_range = ProtoExpert.new("vm110.expert.out_of_range", "Value outside the documented range",
        group.PROTOCOL, severity.WARN),
    unknown_enum = ProtoExpert.new("vm110.expert.unknown_enum", "Unknown enumerated value",
        group.PROTOCOL, severity.WARN),
    disarmed_ru_data = ProtoExpert.new("vm110.expert.disarmed_ru_data", "RU field not zero while no RU is armed",
        group.PROTOCOL, severity.WARN),
    extra_payload = ProtoExpert.new("vm110.expert.extra_payload", "Payload longer than the packet type's layout",
        group.UNDECODED, severity.WARN),
    es_relays_open = ProtoExpert.new("vm110.expert.es_relays_open", "ES-Link relays open",
        group.RESPONSE_CODE, severity.WARN),
}
-- Stream analysis experts (section 7).
local function seq(code, text, sev, grp)
    E[code] = ProtoExpert.new("vm110.expert." .. code, text, grp or group.SEQUENCE, sev or severity.WARN)
end
seq("serial_gap", "Serial gap: packets lost")
seq("serial_duplicate", "Duplicate serial")
seq("serial_out_of_order", "Out-of-order serial")
seq("watchdog_vrpi", "VRPI interval above the controller watchdog")
seq("watchdog_vrpo", "VRPO interval above the base unit watchdog")
seq("vrpo_interval", "VRPO interval outside the recommended range", severity.NOTE)
seq("retransmission", "Command retransmission", severity.NOTE)
seq("resend_interval", "Resend interval far from nominal", severity.NOTE)
seq("spurious_retransmission", "Retransmission after the acknowledgement", severity.NOTE)
seq("ack_without_command", "Acknowledgement without a matching command")
seq("duplicate_ack", "Duplicate acknowledgement", severity.NOTE)
seq("ack_late", "Command not acknowledged in time")
seq("never_acked", "Command never acknowledged in the capture")
seq("burst_missing", "VRPO burst: packet number missing", severity.WARN, group.REASSEMBLE)
seq("burst_incomplete", "Incomplete VRPO burst", severity.WARN, group.REASSEMBLE)
local expert_list = {}
for _, e in pairs(E) do expert_list[#expert_list + 1] = e end
vm110.experts = expert_list

local variant_enum, order_enum = {}, { { "little", "Little-endian (TS-0006 2.1)", 1 }, { "big", "Big-endian", 2 } }
for i, v in ipairs(CRC_VARIANTS) do variant_enum[i] = { v.name, v.label, i } end
vm110.prefs.crc_variant = Pref.enum("CRC variant", 1, "CRC-32 variant the packets are checked with", variant_enum, false)
vm110.prefs.crc_byte_order = Pref.enum("Stored CRC byte order", 1, "Byte order of the CRC trailer", order_enum, false)
vm110.prefs.check_crc = Pref.bool("Validate the CRC", true, "Calculate the CRC of each packet and flag bad ones")
vm110.prefs.input_port = Pref.uint("Input UDP port", DEFAULT_INPUT_PORT,
    "UDP port of input packets; output packets use this port + 2 (TS-0006 2.2)")
vm110.prefs.heuristic = Pref.bool("Find EG-Link on other UDP ports", true,
    "Heuristic: a known packet ID with a size that matches the UDP length")
vm110.prefs.analysis = Pref.bool("Analyse the streams", true,
    "Serial gaps, intervals and watchdogs, retransmissions and acknowledgements, VRPO reassembly")
vm110.prefs.serial_scope = Pref.enum("Serial number scope", 1, "One counter per sender, or one per packet type per sender",
    { { "sender", "Per sender (all packet types)", 1 }, { "type", "Per packet type per sender", 2 } }, false)
vm110.prefs.vrpi_watchdog_ms = Pref.uint("VRPI watchdog (ms)", VRPI_WATCHDOG_MS, "Warn above this VRPI interval")
vm110.prefs.vrpo_watchdog_ms = Pref.uint("VRPO watchdog (ms)", VRPO_WATCHDOG_MS, "Warn above this VRPO interval")
vm110.prefs.vrpo_min_ms = Pref.uint("VRPO recommended minimum interval (ms)", VRPO_PERIOD_MIN_MS, "Note below this")
vm110.prefs.vrpo_max_ms = Pref.uint("VRPO recommended maximum interval (ms)", VRPO_PERIOD_MAX_MS, "Note above this")
vm110.prefs.resend_ms = Pref.uint("Command resend interval (ms)", COMMAND_RESEND_MS, "Nominal resend interval")
vm110.prefs.resend_tolerance_ms = Pref.uint("Resend interval tolerance (ms)", COMMAND_RESEND_MS / 2,
    "Note when a resend interval differs from the nominal one by more than this")
vm110.prefs.vrci_fail_ms = Pref.uint("VRCI failure timeout (ms)", VRCI_FAIL_MS, "Acknowledgement later than this: failed")
vm110.prefs.vrco_give_up_ms = Pref.uint("VRCO give-up timeout (ms)", VRCO_GIVE_UP_MS, "Acknowledgement later than this: late")
vm110.prefs.vrpo_data_size = Pref.uint("Configured periodic data size (bytes)", 0,
    "Total VRPO periodic data of a burst; 0 = infer (a burst ends with a packet of fewer than 488 bytes)")
vm110.prefs.vrpo_number_start = Pref.uint("First VRPO packet number", 0, "Packet number of a burst's first packet (0 or 1)")
vm110.prefs.burst_gap_ms = Pref.uint("VRPO burst gap (ms)", VRPO_BURST_GAP_MS, "A new burst starts after this gap")
vm110.prefs.machine = Pref.string("Machine", "",
    "Key of the machine-specific sub-dissectors in the vm110.periodic_data and vm110.command_data tables")

---------------------------------------------------------------------------------------------
-- 5. Tree and Info column
-- Tree items are the dissector's main cost (each one is a TvbRange and a TreeItem userdata),
-- so the methods are fetched once (`item:add(...)` looks the method up in C on every call)
-- and generated items reuse the range of the bytes they are computed from.
---------------------------------------------------------------------------------------------
local tree_add, tree_add_le, set_generated = TreeItem.add, TreeItem.add_le, TreeItem.set_generated
local add_expert, append_text, tvb_range = TreeItem.add_proto_expert_info, TreeItem.append_text, Tvb.range

-- Bytes outside printable ASCII as \xNN (a packet ID can be anything).
local function printable(text)
    return (text:gsub("[^\32-\126]", function(c) return fmt("\\x%02x", byte(c)) end))
end

local function enum_text(names, value)
    return names[value] or fmt("Unknown (0x%02x)", value)
end

local PROBLEM_TEXT = {
    unknown_id = "unknown packet ID", bad_crc = "bad CRC", revision = "unsupported revision",
    size_mismatch = "size mismatch", size_too_large = "size > 492", truncated = "truncated",
}
local PROBLEM_ORDER = { "unknown_id", "bad_crc", "revision", "size_mismatch", "size_too_large", "truncated" }

local function summary(r)
    local v, id, text = r.values, r.type, nil
    if not r.info then
        text = id and fmt('Unknown packet ID "%s"', printable(id)) or "EG-Link fragment"
    elseif id == "VRPI" and v.bu_state then
        text = "VRPI " .. enum_text(BU_STATE, v.bu_state)
        if v.armed_ru and v.armed_ru ~= 0 then
            text = text .. fmt(" RU 0x%04X", v.armed_ru)
            if v.ru_state then text = text .. " " .. enum_text(RU_STATE, v.ru_state) end
            if v.ru_battery then text = text .. fmt(" bat %d%%", v.ru_battery) end
        elseif v.unarmed_rus then
            text = text .. fmt(" unarmed RUs %d", v.unarmed_rus)
        end
    elseif v.command_id then
        text = fmt((id == "VRCI" or id == "VRCO") and "%s cmd %d" or "%s ack %d", id, v.command_id)
    elseif v.packet_number then
        text = fmt("VRPO #%d %d bytes", v.packet_number, r.data_len)
    else
        text = id
    end
    if r.serial then text = text .. fmt(", serial %d", r.serial) end
    if next(r.problems) then
        local p = {}
        for _, code in ipairs(PROBLEM_ORDER) do
            if r.problems[code] then p[#p + 1] = PROBLEM_TEXT[code] end
        end
        text = text .. " [Illegal: " .. concat(p, ", ") .. "]"
    end
    return text
end

local function field_message(code, name, value)
    local shown = type(value) == "string" and "bytes not zero" or fmt("%d", value)
    if code == "out_of_range" then
        local range = RANGES[name]
        return fmt("vm110.%s = %s is outside %d..%d", name, shown, range[1], range[2])
    elseif code == "unknown_enum" then
        return fmt("vm110.%s = 0x%02x is not a defined value", name, value)
    elseif code == "disarmed_ru_data" then
        return fmt("vm110.%s = %s while vm110.armed_ru = 0", name, shown)
    elseif code == "origin_nonzero" then
        return fmt("vm110.%s = 0x%04x: should be 0 on output packets", name, value)
    end
    return fmt("vm110.%s: %s", name, type(value) == "string" and "bytes not zero" or fmt("0x%x, should be 0", value))
end

local function field_experts(r, item, name, value)
    local codes = r.fieldwarn[name]
    if codes then
        for _, code in ipairs(codes) do add_expert(item, E[code], field_message(code, name, value)) end
    end
end

local function add_undecoded(tree, tvb, off, len, why)
    if len > 0 then return append_text(tree_add(tree, F.undecoded, tvb_range(tvb, off, len)), " (" .. why .. ")") end
end

local function add_header(r, tvb, root)
    local n = r.n
    if r.type then
        local range = tvb_range(tvb, 0, ID_LEN)
        local info = r.info
        local item = tree_add(root, F.type, range, r.type,
            fmt("Packet ID: %s (%s)", printable(r.type), info and info.description or "Unknown"))
        if info then
            set_generated(tree_add(item, F.direction, range, info.direction))
        else
            add_expert(item, E.unknown_id, fmt('Unknown packet ID "%s": the payload is not decoded', printable(r.type)))
        end
    else
        add_undecoded(root, tvb, 0, n, "shorter than a packet ID")
    end
    if n <= ID_LEN then return end
    local hlen = n < PREFIX_LEN and n - ID_LEN or HEADER_LEN
    local header = tree_add(root, tvb_range(tvb, ID_LEN, hlen), "Header")
    local off = ID_LEN
    for _, h in ipairs(HEADER) do
        local name = h[1]
        if not r[name] then break end
        local item = tree_add_le(header, F[name], tvb_range(tvb, h[2], h[3]))
        field_experts(r, item, name, r[name])
        if name == "revision" and r.problems.revision then
            add_expert(item, E.revision, fmt("Revision %d is not supported: only the header is decoded", r.revision))
        elseif name == "size" then
            if r.problems.size_mismatch then
                add_expert(item, E.size_mismatch,
                    fmt("Size %d needs a UDP payload of %d bytes, got %d", r.size, OVERHEAD + r.size, n))
            end
            if r.problems.size_too_large then
                add_expert(item, E.size_too_large, fmt("Size %d is above the maximum of %d", r.size, MAX_PAYLOAD))
            end
        end
        off = h[2] + h[3]
    end
    add_undecoded(header, tvb, off, ID_LEN + hlen - off, "header cut short")
end

local function add_payload(r, tvb, root)
    local info, v, fieldwarn = r.info, r.values, r.fieldwarn
    local plen = r.pay_end - PREFIX_LEN
    local payload = tree_add(root, tvb_range(tvb, PREFIX_LEN, plen), fmt("%s payload (%d bytes)", r.type, plen))
    for _, f in ipairs(r.present) do
        local name = f[1]
        local range = tvb_range(tvb, f.off, f[2])
        local item = tree_add_le(payload, F[name], range)
        if fieldwarn[name] then field_experts(r, item, name, v[name]) end
        if name == "bu_state" then
            local relays = tree_add(payload, F.es_relays_open, range, r.es_relays_open)
            set_generated(relays)
            if r.es_relays_open then
                add_expert(relays, E.es_relays_open,
                    fmt("ES-Link relays open: BU state %s is below Disarmed", enum_text(BU_STATE, v.bu_state)))
            end
        end
    end
    local off = r.decoded_end
    if r.data_len then
        tree_add(payload, F.periodic_data, tvb_range(tvb, off - r.data_len, r.data_len))
    end
    if r.problems.truncated then
        add_expert(payload, E.truncated, fmt("%s payload is %d bytes, its layout needs %d", r.type, plen, info.min))
        add_undecoded(payload, tvb, off, r.pay_end - off, "part of a field")
    elseif r.extra then
        local item = add_undecoded(payload, tvb, off, r.pay_end - off, "beyond the layout")
        add_expert(item, E.extra_payload, fmt("%d bytes beyond the %s layout of %d bytes", r.pay_end - off, r.type, info.max))
    end
end

local CRC_VERDICT = { [CRC_BAD] = " [incorrect]", [CRC_GOOD] = " [correct]", [CRC_UNVERIFIED] = " [unverified]" }

local function add_crc(r, tvb, root)
    local range = tvb_range(tvb, r.crc_off, CRC_LEN)
    local item = tree_add(root, F.crc, range, r.crc, fmt("CRC: 0x%08x%s", r.crc, CRC_VERDICT[r.crc_status]))
    if r.crc_calc then set_generated(tree_add(item, F.crc_calculated, range, r.crc_calc)) end
    set_generated(tree_add(item, F.crc_status, range, r.crc_status))
    if r.crc_status == CRC_BAD then
        add_expert(item, E.bad_crc, fmt("Bad CRC: stored 0x%08x, calculated 0x%08x", r.crc, r.crc_calc))
    end
end

local function add_tree(r, tvb, tree)
    local root = tree_add(tree, vm110, tvb_range(tvb, 0, r.n), "VM-110 EG-Link, " .. r.info_text)
    add_header(r, tvb, root)
    local n = r.n
    if n < PREFIX_LEN then
        add_expert(root, E.truncated, fmt("%d bytes, shorter than the %d-byte packet ID and header", n, PREFIX_LEN))
        return
    end
    if not r.crc_off then
        local item = add_undecoded(root, tvb, PREFIX_LEN, n - PREFIX_LEN, "no room for a CRC") or root
        add_expert(item, E.truncated, fmt("%d bytes, too short for a CRC", n))
        return
    end
    if r.payload then
        add_payload(r, tvb, root)
    else
        add_undecoded(root, tvb, PREFIX_LEN, r.crc_off - PREFIX_LEN, "payload not decoded")
    end
    add_crc(r, tvb, root)
    add_undecoded(root, tvb, r.crc_off + CRC_LEN, n - r.crc_off - CRC_LEN, "after the CRC")
end

---------------------------------------------------------------------------------------------
-- 6. Dissector, registration
---------------------------------------------------------------------------------------------
-- Preferences as plain values: reading vm110.prefs costs C calls on every packet.
local settings = {}
local function read_settings()
    local prefs = vm110.prefs
    settings.variant = prefs.check_crc and CRC_VARIANTS[prefs.crc_variant] or nil
    settings.big_endian = prefs.crc_byte_order == 2
    settings.heuristic = prefs.heuristic
end

-- Calculated CRC per frame and offset (a frame may carry more than one EG-Link packet):
-- re-dissection (GUI clicks, second pass) skips the CRC. Emptied when a capture is (re)loaded
-- and when the preferences change.
local crc_memo = {}

function vm110.init()
    crc_memo = {}
    read_settings()
end

local function dissect(tvb, pinfo, tree)
    local key = pinfo.number * 0x10000 + tvb:offset()
    local r = decode(tvb:raw(), settings.variant, settings.big_endian, pinfo.visited and crc_memo[key] or nil)
    if r.crc_calc then crc_memo[key] = r.crc_calc end
    r.info_text = summary(r)
    local cols = pinfo.cols
    cols.protocol = "VM110"
    cols.info = r.info_text
    add_tree(r, tvb, tree)
    return r.n
end
vm110.dissector = dissect

local function heuristic(tvb, pinfo, tree)
    if not settings.heuristic then return false end
    local n = tvb:len()
    if n < OVERHEAD or n > OVERHEAD + MAX_PAYLOAD or not TYPES[tvb:raw(0, ID_LEN)] then return false end
    if OVERHEAD + tvb(10, 2):le_uint() ~= n then return false end
    dissect(tvb, pinfo, tree) -- not vm110.dissector: that is a handle, and would add the layer twice
    return true
end

local udp_port = DissectorTable.get("udp.port")
local registered_port
local function register_ports()
    local port = floor(vm110.prefs.input_port) -- an integer on Lua 5.4 too
    if port == registered_port then return end
    if registered_port then
        udp_port:remove(registered_port, vm110)
        udp_port:remove(registered_port + OUTPUT_PORT_OFFSET, vm110)
    end
    udp_port:add(port, vm110)
    udp_port:add(port + OUTPUT_PORT_OFFSET, vm110)
    registered_port = port
end

function vm110.prefs_changed()
    crc_memo = {}
    read_settings()
    register_ports()
end

read_settings()
register_ports()
udp_port:add_for_decode_as(vm110)
vm110:register_heuristic("udp", heuristic)
