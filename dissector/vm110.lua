-- Wireshark dissector for the VM-110 UDP EG-Link (TS-0006), following shared/spec/interpretation.md.
--
-- One file on purpose: Wireshark 4.4 loads every .lua in a plugin folder as a plugin.
-- Runs unchanged on Lua 5.2 (Wireshark 4.0) and Lua 5.4 (Wireshark 4.4, 4.6): no bit32, and no
-- 5.3 operators in the source; the CRC's are compiled with load() on Lua 5.3+ only, and on 5.2
-- it uses the `bit` library (LuaBitOp) that Wireshark ships.
--
-- Layout of this file, top to bottom:
--   1. protocol constants (the values and display names of vm110/constants.py)
--   2. CRC engine
--   3. decode(): UDP payload bytes -> a plain record (no Wireshark objects), the rules of
--      vm110/decode.py; a later analysis layer works on these records
--   4. fields, experts, preferences
--   5. tree and Info column built from a record
--   6. preferences as values, per-frame memos; stream analysis (serial numbers, intervals and
--      watchdogs, retransmissions and acknowledgements, VRPO bursts and reassembly, the
--      machine-specific sub-dissector tables vm110.periodic_data / vm110.command_data)
--   7. dissector, heuristic and port registration; statistics (-z vm110,stat, GUI menu)

local PLUGIN_VERSION = "0.1.0"
-- A second copy (an installed plugin and `-X lua_script:` with this file, say) would fail in
-- Proto() with a Lua error and a stack trace; the copy loaded first stays, and this one says so.
-- (Kept in _G: each Lua plugin has an environment of its own.)
do -- (no local of the main chunk: it may have at most 200)
    local this_file, first = debug.getinfo(1, "S").source:gsub("^@", ""), _G.VM110_PLUGIN
    if first then
        report_failure(("vm110: %s not loaded: the VM-110 dissector is loaded already from %s (version %s);"
            .. " remove one of the two"):format(this_file, first.file, first.version))
        return
    end
    _G.VM110_PLUGIN = { file = this_file, version = PLUGIN_VERSION }
end
if set_plugin_info then
    set_plugin_info({
        version = PLUGIN_VERSION,
        description = "VM-110 EG-Link (TS-0006) dissector",
        repository = "vm110 project: dissector/vm110.lua",
    })
end

local byte, sub, fmt, concat = string.byte, string.sub, string.format, table.concat
local floor = math.floor

---------------------------------------------------------------------------------------------
-- 1. Protocol constants
---------------------------------------------------------------------------------------------
-- The fields, enums and layouts come from the Python declaration (pcap_tools/vm110/protocol.py),
-- generated into the marked section below; the rest of this file is written by hand.
-- BEGIN GENERATED TABLES: scripts/lua-tables from pcap_tools/vm110/protocol.py (make lua-tables)
-- Do not edit by hand: change the declaration and run `make lua-tables`.
local ID_LEN, HEADER_LEN, CRC_LEN = 4, 12, 4
local MAX_PAYLOAD = 492
local SUPPORTED_REVISION = 0
-- Value names of the enumerated fields.
local BU_STATE = { [0] = "Initial", [1] = "Stopped", [2] = "External link error", [3] = "Blocked", [4] = "Failed",
    [16] = "Disarmed", [17] = "Armed" }
local LINK_STATUS = { [0] = "Unused", [1] = "Operational", [2] = "No link", [3] = "Link error", [4] = "Interface error",
    [5] = "Data error", [6] = "Passive" }
local RU_STATE = { [0] = "Initial", [1] = "Disarmed", [2] = "Armed", [3] = "Enabled", [4] = "Stopped" }
local RU_CABLE = { [0] = "Wireless", [1] = "Cable" }
local RU_DOCKED = { [0] = "Not docked", [1] = "Docked" }
local RU_DISABLED = { [0] = "Enabled", [1] = "Disabled (tilt)", [2] = "Disabled (inactivity)" }
local ENCODER_SWITCH = { [0] = "Released", [1] = "Pushed" }
-- One table per field: { name, width, kind ("u" unsigned LE, "s" signed LE, "b" bytes), value
-- names or false, off = offset in the packet, pf = ProtoField type, base, label, blurb, range =
-- { low, high } (out_of_range), ru = must be 0 while no RU is armed, spare = should be 0 }.
local FIELDS = {
    revision = { "revision", 2, "u", false, off = 4, pf = "uint16", base = "DEC", label = "Revision",
        blurb = "Header revision; only 0 is defined (any other: illegal, only the header is decoded)" },
    origin = { "origin", 2, "u", false, off = 6, pf = "uint16", base = "HEX", label = "Origin",
        blurb = "Identifies the sending base unit on input packets; 0 on output packets" },
    serial = { "serial", 2, "u", false, off = 8, pf = "uint16", base = "DEC", label = "Serial",
        blurb = "The sender's 16-bit serial counter, one step per packet it sends (wraps 65535 to 0)" },
    size = { "size", 2, "u", false, off = 10, pf = "uint16", base = "DEC", label = "Payload size",
        blurb = "Payload bytes after the 16-byte packet ID and header; the UDP payload is 20 + size (at most 492)" },
    spare = { "spare", 4, "u", false, off = 12, pf = "uint32", base = "HEX", label = "Spare",
        blurb = "Header spare bytes; should be 0", spare = true },
    bu_state = { "bu_state", 1, "u", BU_STATE, off = 16, pf = "uint8", base = "HEX", label = "BU state",
        blurb = "Base unit state" },
    vlaps = { "vlaps", 1, "u", false, off = 17, pf = "uint8", base = "DEC", label = "VLAPs",
        blurb = "Number of VLAPs (0 to 3)", range = { 0, 3 } },
    unarmed_rus = { "unarmed_rus", 1, "u", false, off = 18, pf = "uint8", base = "DEC", label = "Unarmed RUs",
        blurb = "Remote units paired but not armed" },
    eg_link = { "eg_link", 1, "u", LINK_STATUS, off = 19, pf = "uint8", base = "HEX", label = "EG-Link status",
        blurb = "State of the EG-Link (this Ethernet link) as the BU sees it" },
    ec_link = { "ec_link", 1, "u", LINK_STATUS, off = 20, pf = "uint8", base = "HEX", label = "EC-Link status",
        blurb = "State of the EC-Link" },
    c_link = { "c_link", 1, "u", LINK_STATUS, off = 21, pf = "uint8", base = "HEX", label = "C-Link status",
        blurb = "State of the C-Link (radio link to the remote unit)" },
    armed_ru = { "armed_ru", 2, "u", false, off = 22, pf = "uint16", base = "HEX", label = "Armed RU",
        blurb = "ID of the armed remote unit; 0 when none is armed (the RU fields are then 0)" },
    ru_state = { "ru_state", 1, "u", RU_STATE, off = 24, pf = "uint8", base = "HEX", label = "RU state",
        blurb = "State of the armed remote unit", ru = true },
    ru_battery = { "ru_battery", 1, "u", false, off = 25, pf = "uint8", base = "DEC", label = "RU battery (%)",
        blurb = "Battery charge of the armed remote unit, 0 to 100 %", range = { 0, 100 }, ru = true },
    ru_rssi = { "ru_rssi", 1, "u", false, off = 26, pf = "uint8", base = "DEC", label = "RU C-Link RSSI (%)",
        blurb = "Radio signal strength of the armed remote unit, 0 to 100 %", range = { 0, 100 }, ru = true },
    ru_cable = { "ru_cable", 1, "u", RU_CABLE, off = 27, pf = "uint8", base = "HEX", label = "RU cable",
        blurb = "Whether the armed remote unit is connected by cable", ru = true },
    ru_docked = { "ru_docked", 1, "u", RU_DOCKED, off = 28, pf = "uint8", base = "HEX", label = "RU docked",
        blurb = "Whether the armed remote unit is docked", ru = true },
    ru_disabled = { "ru_disabled", 1, "u", RU_DISABLED, off = 29, pf = "uint8", base = "HEX", label = "RU disabled",
        blurb = "Whether the armed remote unit is disabled", ru = true },
    joystick1 = { "joystick1", 2, "s", false, off = 30, pf = "int16", base = "DEC", label = "Joystick 1",
        blurb = "Joystick axis 1 of the remote unit, -1000 to 1000", range = { -1000, 1000 }, ru = true },
    joystick2 = { "joystick2", 2, "s", false, off = 32, pf = "int16", base = "DEC", label = "Joystick 2",
        blurb = "Joystick axis 2 of the remote unit, -1000 to 1000", range = { -1000, 1000 }, ru = true },
    joystick3 = { "joystick3", 2, "s", false, off = 34, pf = "int16", base = "DEC", label = "Joystick 3",
        blurb = "Joystick axis 3 of the remote unit, -1000 to 1000", range = { -1000, 1000 }, ru = true },
    joystick4 = { "joystick4", 2, "s", false, off = 36, pf = "int16", base = "DEC", label = "Joystick 4",
        blurb = "Joystick axis 4 of the remote unit, -1000 to 1000", range = { -1000, 1000 }, ru = true },
    switch1 = { "switch1", 2, "s", false, off = 38, pf = "int16", base = "DEC", label = "Switch 1",
        blurb = "Switch 1 of the remote unit, -1 to 1000", range = { -1, 1000 }, ru = true },
    switch2 = { "switch2", 2, "s", false, off = 40, pf = "int16", base = "DEC", label = "Switch 2",
        blurb = "Switch 2 of the remote unit, -1 to 1000", range = { -1, 1000 }, ru = true },
    switch3 = { "switch3", 2, "s", false, off = 42, pf = "int16", base = "DEC", label = "Switch 3",
        blurb = "Switch 3 of the remote unit, -1 to 1000", range = { -1, 1000 }, ru = true },
    switch4 = { "switch4", 2, "s", false, off = 44, pf = "int16", base = "DEC", label = "Switch 4",
        blurb = "Switch 4 of the remote unit, -1 to 1000", range = { -1, 1000 }, ru = true },
    switch5 = { "switch5", 2, "s", false, off = 46, pf = "int16", base = "DEC", label = "Switch 5",
        blurb = "Switch 5 of the remote unit, -1 to 1000", range = { -1, 1000 }, ru = true },
    switch6 = { "switch6", 2, "s", false, off = 48, pf = "int16", base = "DEC", label = "Switch 6",
        blurb = "Switch 6 of the remote unit, -1 to 1000", range = { -1, 1000 }, ru = true },
    switch7 = { "switch7", 2, "s", false, off = 50, pf = "int16", base = "DEC", label = "Switch 7",
        blurb = "Switch 7 of the remote unit, -1 to 1000", range = { -1, 1000 }, ru = true },
    switch8 = { "switch8", 2, "s", false, off = 52, pf = "int16", base = "DEC", label = "Switch 8",
        blurb = "Switch 8 of the remote unit, -1 to 1000", range = { -1, 1000 }, ru = true },
    encoder = { "encoder", 1, "u", false, off = 54, pf = "uint8", base = "DEC", label = "Encoder value",
        blurb = "Encoder position of the remote unit", ru = true },
    encoder_switch = { "encoder_switch", 1, "u", ENCODER_SWITCH, off = 55, pf = "uint8", base = "HEX",
        label = "Encoder switch", blurb = "Encoder push switch of the remote unit", ru = true },
    vrpi_spare = { "vrpi_spare", 6, "b", false, off = 56, pf = "bytes", base = "NONE", label = "Spare",
        blurb = "VRPI spare bytes; should be 0", spare = true },
    packet_number = { "packet_number", 2, "u", false, off = 16, pf = "uint16", base = "DEC", label = "Packet number",
        blurb = "Number of this packet within its VRPO burst (the first is 0, preference vm110.vrpo_number_start)" },
    periodic_data = { "periodic_data", 488, "b", false, off = 18, pf = "bytes", base = "NONE", label = "Periodic data",
        blurb = "Machine-specific display data (up to 488 bytes per packet; split bursts are reassembled)" },
    command_id = { "command_id", 2, "u", false, off = 16, pf = "uint16", base = "DEC", label = "Command ID",
        blurb = "Pairs a command (VRCI, VRCO) with its acknowledgement (VRAO, VRAI); the same ID again is a resend" },
    command_spare = { "command_spare", 4, "u", false, off = 18, pf = "uint32", base = "HEX", label = "Spare",
        blurb = "Command spare bytes; should be 0", spare = true },
    command_data = { "command_data", 16, "b", false, off = 22, pf = "bytes", base = "NONE", label = "Command data",
        blurb = "16 bytes of machine-specific command data" },
}
local HEADER = { FIELDS.revision, FIELDS.origin, FIELDS.serial, FIELDS.size, FIELDS.spare }
-- Payload layouts: the fields in wire order.
local VRPI_LAYOUT = { FIELDS.bu_state, FIELDS.vlaps, FIELDS.unarmed_rus, FIELDS.eg_link, FIELDS.ec_link, FIELDS.c_link,
    FIELDS.armed_ru, FIELDS.ru_state, FIELDS.ru_battery, FIELDS.ru_rssi, FIELDS.ru_cable, FIELDS.ru_docked,
    FIELDS.ru_disabled, FIELDS.joystick1, FIELDS.joystick2, FIELDS.joystick3, FIELDS.joystick4, FIELDS.switch1,
    FIELDS.switch2, FIELDS.switch3, FIELDS.switch4, FIELDS.switch5, FIELDS.switch6, FIELDS.switch7, FIELDS.switch8,
    FIELDS.encoder, FIELDS.encoder_switch, FIELDS.vrpi_spare }
local VRPO_LAYOUT = { FIELDS.packet_number }
local COMMAND_LAYOUT = { FIELDS.command_id, FIELDS.command_spare, FIELDS.command_data }
local ACK_LAYOUT = { FIELDS.command_id }
-- Packet types: { ID, description, layout, tail (up to its width of bytes after the layout) or false,
-- the field whose 0 means no RU is armed or false }.
local PACKET_TYPES = {
    { "VRPI", "VisionRemote Periodic Input", VRPI_LAYOUT, false, "armed_ru" },
    { "VRPO", "VisionRemote Periodic Output", VRPO_LAYOUT, FIELDS.periodic_data, false },
    { "VRCI", "VisionRemote Command Input", COMMAND_LAYOUT, false, false },
    { "VRCO", "VisionRemote Command Output", COMMAND_LAYOUT, false, false },
    { "VRAI", "VisionRemote Acknowledge Input", ACK_LAYOUT, false, false },
    { "VRAO", "VisionRemote Acknowledge Output", ACK_LAYOUT, false, false },
}
-- END GENERATED TABLES
local PREFIX_LEN = ID_LEN + HEADER_LEN
local OVERHEAD = PREFIX_LEN + CRC_LEN
local VRPO_MAX_DATA = FIELDS.periodic_data[2]
local VRPO_HEADER_SIZE = FIELDS.periodic_data.off - PREFIX_LEN
-- Where generated fields point: the serial (serial analysis), the packet number (VRPO bursts).
local SERIAL_OFF, SERIAL_LEN = FIELDS.serial.off, FIELDS.serial[2]
local NUMBER_OFF, NUMBER_LEN = FIELDS.packet_number.off, FIELDS.packet_number[2]
local DEFAULT_INPUT_PORT, OUTPUT_PORT_OFFSET = 5825, 2
-- Timing and numbering of section 5.1 (interpretation.md "Timing", "Serial numbers", "VRPO split").
local VRPI_WATCHDOG_MS, VRPO_WATCHDOG_MS, VRPO_PERIOD_MIN_MS, VRPO_PERIOD_MAX_MS = 500, 2000, 50, 200
local COMMAND_RESEND_MS, VRCI_FAIL_MS, VRCO_GIVE_UP_MS, VRPO_BURST_GAP_MS = 100, 2000, 2000, 20
local SERIAL_MODULUS, SERIAL_HALF = 65536, 32768
-- docs/rules.md: duplicate window, command ID reuse gap, restart on a new port after this silence,
-- the rate window of the plausible-gap test and its constants (d - 1 <= 64 + 4 max(r, 20) dt), a
-- restart confirmed by the next serial s + 1 ... s + 4, which changes commands only when it comes
-- less than 10 s after the candidate (the command events behind a candidate wait that long at most).
local RULES = { dup_window_ms = 1000, reuse_gap_ms = 2000, new_port_silence_ms = 250, rate_window_s = 10,
    gap_slack = 64, gap_rate_factor = 4, gap_min_rate = 20, confirm_span = 4, candidate_wait_ms = 10000 }
local ACK_OF = { VRAO = "VRCI", VRAI = "VRCO" }
local ES_RELAYS_CLOSED_FROM = 0x10

local CRC_STATUS = { [0] = "Bad", [1] = "Good", [2] = "Unverified" }
local CRC_BAD, CRC_GOOD, CRC_UNVERIFIED = 0, 1, 2

local function layout_size(layout)
    local size = 0
    for _, f in ipairs(layout) do size = size + f[2] end
    return size
end

-- tshark's command line, when this process is tshark (/proc/self/cmdline: Linux): option letter
-- -> its value (the last given) or true; `words`: every argument, space-separated. nil elsewhere.
-- Only for choices that cannot be made otherwise: which fields 4.0's -T fields prints (section
-- 5), and whether this is a single pass (sections 5 and 6: each frame dissected once, with one
-- tree; the capture's end read by the statistics alone).
local TSHARK_OPTIONS
do
    local file = io.open("/proc/self/cmdline", "rb")
    local line = file and file:read("*a") or ""
    if file then file:close() end
    local argv = {}
    for a in line:gmatch("([^\0]*)\0") do argv[#argv + 1] = a end
    if argv[1] and argv[1]:match("tshark[^/]*$") then
        -- getopt over tshark's options: those that take a value, so that a value is never an option
        local WITH_VALUE = "aAbBcCdeEfFGHiIjJKMNoOrRsStTuUwWXyYz"
        local opts, i = { words = " " .. line:gsub("\0", " ") .. " " }, 2
        while i <= #argv do
            local a = argv[i]
            if a == "--" then break end
            if a:sub(1, 2) == "--" then
                if not a:find("=", 1, true) and argv[i + 1] and argv[i + 1]:sub(1, 1) ~= "-" then i = i + 1 end
            elseif a:sub(1, 1) == "-" then
                for j = 2, #a do
                    local opt = a:sub(j, j)
                    if WITH_VALUE:find(opt, 1, true) then
                        local value = a:sub(j + 1)
                        if value == "" then
                            i = i + 1
                            value = argv[i] or ""
                        end
                        opts[opt] = value
                        break
                    end
                    opts[opt] = true
                end
            end
            i = i + 1
        end
        -- A single pass (no -2) dissects each frame once, all with one tree of fixed visibility.
        opts.single_pass = not opts["2"]
        TSHARK_OPTIONS = opts
    end
end

-- Packet types by ID. min/max: payload sizes; the 4th ID character gives the direction.
local TYPES = {}
for _, t in ipairs(PACKET_TYPES) do
    local min = layout_size(t[3])
    TYPES[t[1]] = {
        id = t[1], layout = t[3], min = min, max = min + (t[4] and t[4][2] or 0), ru_gate = t[5],
        direction = sub(t[1], 4, 4) == "I" and "Input" or "Output",
        label = fmt("Packet ID: %s (%s)", t[1], t[2]), -- (tree labels made once, not per packet)
        payload_labels = setmetatable({}, { __index = function(labels, len)
            labels[len] = fmt("%s payload (%d bytes)", t[1], len)
            return labels[len]
        end }),
    }
end

---------------------------------------------------------------------------------------------
-- 2. CRC engine
-- Slicing by 16: a block of up to 16 bytes takes one string.byte call and one lookup per byte
-- in 256-entry tables (S[j][v]: the register after the rest of a 16-byte block when byte j of
-- the block, j = 0 first, is v and everything else is zero; S[15] is the byte-at-a-time table;
-- by linearity the register after a block is the XOR of S[j][x_j], x = the block with the
-- register XORed into its first four bytes; a block of n bytes uses S[16 - n .. 15]). The
-- remainder of a packet (4 to 15 bytes) is one such block too, and the code per block length
-- is generated, like the payload readers.
-- Lua 5.3 and later (Wireshark 4.4, 4.6): native integer operators (~, >>, &), compiled with
-- load() so that this file still parses on Lua 5.2: no C call but string.byte.
-- Lua 5.2 (Wireshark 4.0): no such operators, and C calls, not arithmetic, are what costs
-- there: the XOR of a block's 16 lookups is one call of the `bit` library (LuaBitOp, shipped
-- with Wireshark), so a block costs three C calls in all, never one per byte. (Byte-at-a-time
-- XOR by table lookup, a 64K-entry table, measured slower inside tshark: cache misses.)
-- Each variant gets `calc(s, len)`: the CRC of the first len bytes of s, unsigned, the final XOR
-- included. All state of this section stays in one block (the main chunk may have at most 200
-- locals).
---------------------------------------------------------------------------------------------
-- CRC variants of interpretation.md: all with init 0xFFFFFFFF and polynomial 0x04C11DB7.
local CRC_VARIANTS = {
    { name = "mpeg2", label = "CRC-32/MPEG-2 (default)", reflected = false, xorout = false },
    { name = "iso-hdlc", label = "CRC-32/ISO-HDLC (zlib)", reflected = true, xorout = true },
    { name = "bzip2", label = "CRC-32/BZIP2", reflected = false, xorout = true },
    { name = "jamcrc", label = "CRC-32/JAMCRC", reflected = true, xorout = false },
}
local NATIVE_INTEGERS = _VERSION >= "Lua 5.3" -- ("Lua 5.2" < "Lua 5.3" < "Lua 5.4")
do
    local SLICES = 16

    -- The tables, built for a variant's bit order when it is first used: S[j][v] as unsigned
    -- numbers. XOR of two unsigned 32-bit numbers: native on Lua 5.3+, LuaBitOp's (signed) on 5.2.
    local xor32
    if NATIVE_INTEGERS then
        xor32 = assert(load("return function(a, b) return a ~ b end", "=vm110 xor", "t", {}))()
    else
        local bxor = (bit or require("bit")).bxor
        function xor32(a, b)
            local x = bxor(a, b)
            if x < 0 then x = x + 4294967296 end
            return x
        end
    end
    local function build_tables(reflected)
        local T = {}
        for v = 0, 255 do
            local r = reflected and v or v * 16777216
            for _ = 1, 8 do
                if reflected then
                    local low = r % 2
                    r = (r - low) / 2
                    if low ~= 0 then r = xor32(r, 0xEDB88320) end
                else
                    local high = r >= 0x80000000
                    r = (r % 0x80000000) * 2
                    if high then r = xor32(r, 0x04C11DB7) end
                end
            end
            T[v] = floor(r)
        end
        local S = { [SLICES - 1] = T }
        for j = SLICES - 2, 0, -1 do
            local next_, this = S[j + 1], {}
            for v = 0, 255 do -- one zero byte more through the register
                local r = next_[v]
                if reflected then
                    local low = r % 256
                    this[v] = floor(xor32((r - low) / 256, T[low]))
                else
                    local high = (r - r % 16777216) / 16777216
                    this[v] = floor(xor32((r % 16777216) * 256, T[high]))
                end
            end
            S[j] = this
        end
        return S
    end

    -- Lua source of one block of n (4..16) bytes at s[i]: updates r. The register's byte consumed
    -- first is its low byte when reflected, its high byte otherwise.
    local function block_source(n, reflected)
        local b, lookups = {}, {}
        for j = 1, n do b[j] = "b" .. j end
        local word, order
        if NATIVE_INTEGERS then
            word = reflected and "b1 | b2 << 8 | b3 << 16 | b4 << 24" or "b1 << 24 | b2 << 16 | b3 << 8 | b4"
            order = reflected and { "x & 255", "x >> 8 & 255", "x >> 16 & 255", "x >> 24" }
                or { "x >> 24", "x >> 16 & 255", "x >> 8 & 255", "x & 255" }
        else
            word = reflected and "((b4 * 256 + b3) * 256 + b2) * 256 + b1" or "((b1 * 256 + b2) * 256 + b3) * 256 + b4"
            order = reflected and { "x0", "x1", "x2", "x3" } or { "x3", "x2", "x1", "x0" }
        end
        for j = 1, n do
            lookups[j] = fmt("S%d[%s]", SLICES - n + j - 1, j <= 4 and order[j] or b[j])
        end
        local code = fmt("local %s = byte(s, i, i + %d)\n", concat(b, ", "), n - 1)
        if NATIVE_INTEGERS then
            return code .. fmt("local x = r ~ (%s)\nr = %s\n", word, concat(lookups, " ~ "))
        end
        return code .. fmt("local x = bxor(r, %s)\nif x < 0 then x = x + 4294967296 end\n", word)
            .. "local x0 = x % 256\nx = (x - x0) / 256\nlocal x1 = x % 256\nx = (x - x1) / 256\n"
            .. "local x2 = x % 256\nlocal x3 = (x - x2) / 256\n"
            .. fmt("r = bxor(%s)\n", concat(lookups, ", "))
    end

    -- calc(s, len) of one variant.
    local function build_crc(reflected, xorout, S)
        local tables, upvalues = {}, {}
        for j = 0, SLICES - 1 do tables[j + 1], upvalues[j + 1] = "S" .. j, "U" .. j end
        local tails = {}
        for n = SLICES - 1, 4, -1 do
            tails[#tails + 1] = fmt("%s t == %d then\n%s", n == SLICES - 1 and "if" or "elseif", n,
                block_source(n, reflected))
        end
        local byte_step, finish
        if NATIVE_INTEGERS then
            byte_step = reflected and "r = r >> 8 ~ S15[(r ~ byte(s, j)) & 255]"
                or "r = (r << 8 & 0xFFFFFFFF) ~ S15[r >> 24 ~ byte(s, j)]"
            finish = xorout and "return r ~ 0xFFFFFFFF\n" or "return r\n"
        else
            byte_step = reflected and "r = bxor(rshift(r, 8), S15[bxor(band(r, 255), byte(s, j))])"
                or "r = bxor(lshift(r, 8), S15[bxor(rshift(r, 24), byte(s, j))])"
            finish = "if r < 0 then r = r + 4294967296 end\n"
                .. (xorout and "return 4294967295 - r\n" or "return r\n")
        end
        -- (the tables in registers: an upvalue costs an instruction more per lookup)
        local code = fmt("local byte, bxor, band, lshift, rshift, %s = ...\n", concat(upvalues, ", "))
            .. fmt("return function(s, len)\nlocal %s = %s\n", concat(tables, ", "), concat(upvalues, ", "))
            .. fmt("local r, i = %s, 1\nwhile i + 15 <= len do\n", NATIVE_INTEGERS and "0xFFFFFFFF" or "-1")
            .. block_source(SLICES, reflected) .. "i = i + 16\nend\nlocal t = len - i + 1\n"
            .. concat(tails) .. fmt("else\nfor j = i, len do %s end\nend\n", byte_step)
            .. finish .. "end\n"
        local args = { byte, false, false, false, false }
        if not NATIVE_INTEGERS then
            local bit = bit or require("bit")
            args[2], args[3], args[4], args[5] = bit.bxor, bit.band, bit.lshift, bit.rshift
        end
        for j = 0, SLICES - 1 do
            local t = S[j]
            if not NATIVE_INTEGERS then -- (LuaBitOp's registers are signed 32 bits)
                t = {}
                for v = 0, 255 do t[v] = S[j][v] >= 0x80000000 and S[j][v] - 4294967296 or S[j][v] end
            end
            args[#args + 1] = t
        end
        return assert(load(code, "=vm110 crc", "t", {}))(table.unpack(args, 1, 5 + SLICES))
    end

    -- A variant's calc, compiled when first asked for: a tshark run uses one of the four.
    local tables = {}
    local LAZY_CALC = { __index = function(v, key)
        if key ~= "calc" then return nil end
        tables[v.reflected] = tables[v.reflected] or build_tables(v.reflected)
        local calc = build_crc(v.reflected, v.xorout, tables[v.reflected])
        rawset(v, "calc", calc)
        return calc
    end }
    for _, v in ipairs(CRC_VARIANTS) do setmetatable(v, LAZY_CALC) end
end

---------------------------------------------------------------------------------------------
-- 3. decode(): the rules of vm110/decode.py, on a Lua string
-- Record (false = absent): n, type, info (TYPES entry), header values (revision ... spare),
-- crc_off (offset of the CRC), crc, crc_calc, crc_status, pay_end (end of the payload span),
-- payload (true when the payload is decoded), values (layout field -> value), present (layout
-- entries decoded), decoded_end, data_len (VRPO periodic data: the data_len bytes before
-- decoded_end), es_relays_open,
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

-- A reader per layout for whole payloads: one string.byte call into locals, stored into the
-- given table (a packet type's own, reused: a new table per packet is work for the collector),
-- no loop. Generated from the layout, so that the layout stays the only description of each
-- packet.
local function compile_reader(layout)
    local parts, locals, off = {}, {}, PREFIX_LEN
    for _, f in ipairs(layout) do
        local name, width, kind = f[1], f[2], f[3]
        local expr
        if kind == "b" then
            expr = fmt("sub(s, %d, %d)", off + 1, off + width)
        elseif width == 1 then
            expr = fmt("b%d", off + 1)
        elseif width == 2 then
            expr = fmt("b%d + b%d * 256", off + 1, off + 2)
            if kind == "s" then -- (the sign from the high byte inline: a call per field costs more)
                expr = fmt("b%d < 128 and %s or %s - 65536", off + 2, expr, expr)
            end
        else
            expr = fmt("((b%d * 256 + b%d) * 256 + b%d) * 256 + b%d", off + 4, off + 3, off + 2, off + 1)
        end
        parts[#parts + 1] = "v." .. name .. " = " .. expr
        off = off + width
    end
    for i = PREFIX_LEN + 1, off do locals[#locals + 1] = "b" .. i end
    local code = fmt("local byte, sub = ...\nreturn function(s, v)\nlocal %s = byte(s, %d, %d)\n"
        .. "%s\nreturn v\nend", concat(locals, ", "), PREFIX_LEN + 1, off, concat(parts, "\n"))
    return assert(load(code, "=vm110 reader", "t", {}))(byte, sub)
end

-- The problems, warnings or values of a packet that has none: shared, never written (most
-- packets have no problem and no warning).
local EMPTY = {}

-- The record's own table at `key` (problems, fieldwarn), made on the first write.
local function own(r, key)
    local t = r[key]
    if t == EMPTY then
        t = {}
        r[key] = t
    end
    return t
end

local function problem(r, code)
    own(r, "problems")[code] = true
end

local function warn(r, field, code)
    local fieldwarn = own(r, "fieldwarn")
    local list = fieldwarn[field]
    if not list then
        list = {}
        fieldwarn[field] = list
    end
    list[#list + 1] = code
end

-- The value checks of a layout as straight-line code, generated from its field tables (like the
-- readers): spare fields not 0, values outside the value names or the documented range, RU
-- fields set while the gate field (armed_ru) is 0. A loop over the fields would cost several
-- lookups per field on every packet. False when the layout has nothing to check.
local function compile_checks(layout, gate)
    local lines, consts = { "local warn, consts = ...", "return function(r, v)" }, {}
    if gate then lines[#lines + 1] = fmt("local disarmed = v.%s == 0", gate) end
    local any = false
    for i, f in ipairs(layout) do
        local name, tests = f[1], {}
        if f.spare then
            consts[i] = f[3] == "b" and string.rep("\0", f[2]) or 0
            tests[#tests + 1] = fmt('if x ~= consts[%d] then warn(r, "%s", "spare_nonzero") end', i, name)
        end
        if f[4] then
            consts[i] = f[4]
            tests[#tests + 1] = fmt('if consts[%d][x] == nil then warn(r, "%s", "unknown_enum") end', i, name)
        end
        if f.range then
            tests[#tests + 1] = fmt('if x < %d or x > %d then warn(r, "%s", "out_of_range") end',
                f.range[1], f.range[2], name)
        end
        if f.ru and gate then
            tests[#tests + 1] = fmt('if disarmed and x ~= 0 then warn(r, "%s", "disarmed_ru_data") end', name)
        end
        if #tests > 0 then
            any = true
            lines[#lines + 1] = fmt("do local x = v.%s if x ~= nil then %s end end", name, concat(tests, " "))
        end
    end
    lines[#lines + 1] = "end"
    return any and assert(load(concat(lines, "\n"), "=vm110 checks", "t", {}))(warn, consts)
end

local function check_values(r, info)
    if info.check then info.check(r, r.values) end
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
        v = info.read(s, info.values)
        r.present, r.decoded_end = info.layout, PREFIX_LEN + info.min
    else
        problem(r, "truncated")
        v, r.present, r.decoded_end = read_partial(s, info.layout, limit)
    end
    r.values = v
    if info.id == "VRPO" and v.packet_number then
        local off = r.decoded_end
        local len = limit - off
        if len > VRPO_MAX_DATA then len = VRPO_MAX_DATA end
        r.data_len = len -- (the data are read from the packet where needed, not copied per packet)
        r.decoded_end = off + len
    elseif info.id == "VRPI" and v.bu_state then
        r.es_relays_open = v.bu_state < ES_RELAYS_CLOSED_FROM
    end
end

-- Each type gets its reader and values table; layout entries get their offset in the packet
-- (for the tree).
for _, info in pairs(TYPES) do
    info.read, info.values = compile_reader(info.layout), {}
    info.check = compile_checks(info.layout, info.ru_gate)
end

-- s: the UDP payload; variant: a CRC_VARIANTS entry, or nil when validation is off;
-- big_endian: stored CRC byte order; known_crc: the calculated CRC when memoised, true when it
-- is known to match the stored one. A whole payload's values are its type's table, valid until
-- the next packet of that type is decoded: nothing reads them after a machine sub-dissector (which
-- could dissect another packet) has run.
-- The record is one table, reused (a table of 24 keys per packet was garbage that the collector
-- had to sweep: the largest allocation per packet): valid until the next packet is decoded.
-- machine_data.dissect() puts a new one in place before a machine sub-dissector runs (which could
-- dissect another packet while the caller still reads its own).
local function new_record()
    return { n = 0, problems = EMPTY, fieldwarn = EMPTY, values = EMPTY, type = false, info = false,
        revision = false, origin = false, serial = false, size = false, spare = false, crc_off = false,
        pay_end = false, crc = false, crc_calc = false, crc_status = false, payload = false, present = false,
        decoded_end = false, data_len = false, extra = false, es_relays_open = false, info_text = false,
        cut = false }
end
local record = new_record()

-- `cut`: the capture holds less of the datagram than was sent: "snaplen" (the capture's snaplen
-- cut it), "fragment" (the first IP fragment of a datagram not reassembled, as with
-- ip.defragment off) or "quote" (an ICMP error quoted only its beginning). A packet so shortened
-- is illegal as truncated, and nothing else of it is judged (its CRC and size are not there).
local function decode(s, variant, big_endian, known_crc, cut)
    local n = #s
    local r = record
    -- (each field is set on every path: the header's and the CRC's where they are read)
    r.n, r.problems, r.fieldwarn, r.values, r.type, r.info, r.cut = n, EMPTY, EMPTY, EMPTY, false, false, false
    r.payload, r.present, r.decoded_end, r.data_len, r.extra, r.es_relays_open, r.info_text =
        false, false, false, false, false, false, false
    local info
    if n >= ID_LEN then
        r.type = sub(s, 1, ID_LEN)
        info = TYPES[r.type]
        r.info = info
        if not info then problem(r, "unknown_id") end
    end
    if n < PREFIX_LEN then
        r.revision, r.origin, r.serial, r.size, r.spare = false, false, false, false, false
        r.crc_off, r.pay_end, r.crc, r.crc_calc, r.crc_status = false, false, false, false, false
        for _, h in ipairs(HEADER) do
            if h.off + h[2] > n then break end
            r[h[1]] = h[2] == 2 and u16(s, h.off) or u32(s, h.off)
        end
        if cut then r.cut, r.problems = cut, EMPTY end -- (cut short: truncated, and for that alone)
        problem(r, "truncated")
        return r
    end
    local r1, r2, o1, o2, s1, s2, z1, z2, p1, p2, p3, p4 = byte(s, 5, PREFIX_LEN)
    local revision, origin, size = r1 + r2 * 256, o1 + o2 * 256, z1 + z2 * 256
    local spare = ((p4 * 256 + p3) * 256 + p2) * 256 + p1
    r.revision, r.origin, r.serial, r.size, r.spare = revision, origin, s1 + s2 * 256, size, spare
    if cut and n < OVERHEAD + size then
        r.crc_off, r.pay_end, r.crc, r.crc_calc, r.crc_status = false, false, false, false, false
        r.cut, r.problems = cut, EMPTY
        problem(r, "truncated")
        return r
    end
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
            local calc = known_crc == true and r.crc or known_crc or variant.calc(s, off)
            r.crc_calc = calc
            if calc == r.crc then
                r.crc_status = CRC_GOOD
            else
                r.crc_status = CRC_BAD
                problem(r, "bad_crc")
            end
        else
            r.crc_calc, r.crc_status = false, CRC_UNVERIFIED
        end
    else
        r.crc_off, r.pay_end, r.crc, r.crc_calc, r.crc_status = false, false, false, false, false
    end
    if revision ~= SUPPORTED_REVISION then problem(r, "revision") end
    if n ~= OVERHEAD + size then problem(r, "size_mismatch") end
    if size > MAX_PAYLOAD then problem(r, "size_too_large") end
    if spare ~= 0 then warn(r, "spare", "spare_nonzero") end
    if origin ~= 0 and info and info.direction == "Output" then warn(r, "origin", "origin_nonzero") end
    if n < OVERHEAD then
        problem(r, "truncated") -- no room for a CRC: nothing after the header
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

-- Every field has a description (blurb): the status bar shows it, and `tshark -G fields` lists it.
local F = {
    type = ProtoField.string("vm110.type", "Packet ID", base.NONE,
        "The 4-character packet ID: VRPI, VRPO, VRCI, VRCO, VRAI or VRAO (TS-0006 3)"),
    direction = ProtoField.string("vm110.direction", "Direction", base.NONE,
        "Input (BU to controller) or Output (controller to BU), from the packet ID's 4th character"),
    crc = ProtoField.uint32("vm110.crc", "CRC", base.HEX, nil, nil,
        "CRC-32 trailer over packet ID, header and payload, as stored (preferences: variant, byte order)"),
    crc_calculated = ProtoField.uint32("vm110.crc.calculated", "Calculated CRC", base.HEX, nil, nil,
        "The CRC-32 calculated over packet ID, header and payload"),
    crc_status = ProtoField.uint8("vm110.crc.status", "CRC status", base.DEC, CRC_STATUS, nil,
        "0 Bad, 1 Good, 2 Unverified (CRC validation off)"),
    undecoded = ProtoField.bytes("vm110.undecoded", "Undecoded bytes", base.NONE,
        "Bytes no field owns: a payload not decoded, a field cut short, bytes beyond the layout or after the CRC"),
    -- VRPI, derived from bu_state
    es_relays_open = ProtoField.bool("vm110.es_relays_open", "ES-Link relays open", base.NONE, nil, nil,
        "True when the BU state is below Disarmed: the emergency-stop relays are open"),
}
-- The header and payload fields, one per field table of section 1.
for name, f in pairs(FIELDS) do
    local abbr = "vm110." .. name
    if f[3] == "b" then
        F[name] = ProtoField.bytes(abbr, f.label, base[f.base], f.blurb)
    else
        F[name] = ProtoField[f.pf](abbr, f.label, base[f.base], f[4] or nil, nil, f.blurb)
    end
end
-- Stream analysis (section 7): generated fields, all computed from earlier frames of the capture.
local frametypes = frametype or {} -- framenum types (arrows in the GUI) where this Wireshark has them
F.analysis_flags = ProtoField.string("vm110.analysis.flags", "VM-110 analysis flags", base.NONE,
    "The stream analysis's findings on this packet, comma-separated (present on every packet with one)")
F.serial_missing = ProtoField.uint32("vm110.analysis.serial_missing", "Packets missing before this one", base.DEC,
    nil, nil, "Serials this packet jumped over (lost, at detection; a late packet may fill the gap later)")
F.serial_duplicate = ProtoField.uint8("vm110.analysis.serial_duplicate", "Duplicate serial", base.DEC, nil, nil,
    "1: a serial the counter accepted less than the duplicate window ago (a copy: takes no part in the analysis)")
F.serial_out_of_order = ProtoField.uint8("vm110.analysis.serial_out_of_order", "Out-of-order (late) serial",
    base.DEC, nil, nil, "1: late (fills a gap opened within the duplicate window) or an unconfirmed restart candidate")
F.interval = ProtoField.double("vm110.analysis.interval", "Interval since the previous packet of this type (ms)",
    "ms since the sender's previous accepted VRPI (VRPO); above the watchdog limit a watchdog violation")
F.retransmission_of = ProtoField.framenum("vm110.analysis.retransmission_of", "Retransmission of frame",
    base.NONE, frametypes.RETRANS_PREV, nil, "Frame of this command's first transmission")
F.retransmission_number = ProtoField.uint16("vm110.analysis.retransmission_number", "Retransmission number", base.DEC,
    nil, nil, "1 for the first resend of a command, 2 for the second, ...")
F.since_first = ProtoField.double("vm110.analysis.since_first", "Time since the first transmission (ms)",
    "ms since this command's first transmission")
F.resend_interval = ProtoField.double("vm110.analysis.resend_interval", "Time since the previous transmission (ms)",
    "ms since this command's previous transmission (nominal 100 ms)")
F.ack_in = ProtoField.framenum("vm110.analysis.ack_in", "Acknowledged in frame", base.NONE, frametypes.ACK, nil,
    "Frame of the command's first acknowledgement")
F.ack_to = ProtoField.framenum("vm110.analysis.ack_to", "Acknowledges the command of frame", base.NONE,
    frametypes.REQUEST, nil, "Frame of the first transmission of the command this acknowledges")
F.ack_time = ProtoField.double("vm110.analysis.ack_time", "Acknowledged after, from the first transmission (ms)",
    "ms from the command's first transmission to this acknowledgement")
F.ack_time_last = ProtoField.double("vm110.analysis.ack_time_last",
    "Acknowledged after, from the last transmission (ms)",
    "ms from the command's last transmission before this acknowledgement")
F.burst_interval = ProtoField.double("vm110.analysis.burst_interval",
    "Interval since the first packet of the previous VRPO burst (ms)",
    "The VRPO period: ms between the first packets of consecutive bursts (recommended 50 to 200 ms)")
F.restart = ProtoField.uint16("vm110.analysis.restart", "Sender restart: the highest serial before it", base.DEC,
    nil, nil, "Where a sender restarted (its serial counter started afresh): the highest serial before")
F.restart_port_from = ProtoField.uint16("vm110.analysis.restart_port_from",
    "Sender restart: UDP source port before it", base.DEC, nil, nil,
    "A sender that came back on a new UDP source port: the port it used before")
F.silent_until_end = ProtoField.double("vm110.analysis.silent_until_end",
    "Stream silent from here to the end of the capture (ms)",
    "On a periodic stream's last packet: ms to the capture's last record, when above the watchdog limit")
F.interrupted_by = ProtoField.framenum("vm110.analysis.interrupted_by", "Interrupted by the sender's restart in frame",
    base.NONE, nil, nil, "Frame of the sender's restart that ended this unacknowledged command")
F.burst_packets = ProtoField.uint16("vm110.burst.packets", "VRPO packets in the burst", base.DEC, nil, nil,
    "VRPO packets of this burst so far (packets less than the burst gap apart)")
F.burst_size = ProtoField.uint32("vm110.burst.size", "Periodic data in the burst (bytes)", base.DEC, nil, nil,
    "Periodic data bytes of this burst so far")
F.burst_frame = ProtoField.framenum("vm110.burst.frame", "VRPO packet in frame", base.NONE, nil, nil,
    "A frame holding a packet of this burst (up to 64 listed)")
F.burst_complete = ProtoField.bool("vm110.burst.complete", "Burst complete", base.NONE, nil, nil,
    "On a burst's last packet: every packet number present, all but the last carrying 488 bytes")
F.reassembled = ProtoField.bytes("vm110.reassembled", "Reassembled periodic data", base.NONE,
    "The periodic data of a complete burst in packet-number order")
-- In name order: `tshark -G fields` then lists them the same way on every run (pairs() order
-- changes from run to run on Lua 5.4).
do
    local field_list, field_names = {}, {}
    for name in pairs(F) do field_names[#field_names + 1] = name end
    table.sort(field_names)
    for i, name in ipairs(field_names) do field_list[i] = F[name] end
    vm110.fields = field_list
end

-- One expert per problem and warning code of vm110.decode(): abbrev "vm110.expert.<code>". An item
-- added with the registered summary reads the same in Analyze > Expert Information (which groups by
-- expert and shows that summary) and in tshark -z expert (which groups by the item's text).
local group, severity = expert.group, expert.severity
local E = {
    unknown_id = ProtoExpert.new("vm110.expert.unknown_id", "Unknown packet ID: the payload is not decoded",
        group.PROTOCOL, severity.ERROR),
    bad_crc = ProtoExpert.new("vm110.expert.bad_crc", "Bad CRC", group.CHECKSUM, severity.ERROR),
    revision = ProtoExpert.new("vm110.expert.revision", "Unsupported revision: only the header is decoded",
        group.PROTOCOL, severity.ERROR),
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
    es_relays_open = ProtoExpert.new("vm110.expert.es_relays_open", "ES-Link relays open: BU state below Disarmed",
        group.RESPONSE_CODE, severity.WARN),
}
-- Stream analysis experts (section 7). Each has the severity of `vm110 analyze`'s finding of the
-- same rule: an error where TS-0006 has an end flag an error (watchdogs, a command not acknowledged
-- in time or never), a note where Wireshark's TCP analysis has one (retransmissions, duplicate acks).
local function seq(code, text, sev, grp)
    E[code] = ProtoExpert.new("vm110.expert." .. code, text, grp or group.SEQUENCE, sev or severity.WARN)
end
seq("serial_gap", "Serial gap: packets missing")
seq("serial_duplicate", "Duplicate serial")
seq("serial_out_of_order", "Out-of-order serial")
seq("watchdog_vrpi", "VRPI interval above the controller watchdog", severity.ERROR)
seq("watchdog_vrpo", "VRPO interval above the base unit watchdog", severity.ERROR)
seq("vrpo_interval", "VRPO interval outside the recommended range", severity.NOTE)
seq("time_backwards", "Timestamp earlier than the stream's previous packet")
seq("retransmission", "Command retransmission", severity.NOTE)
seq("resend_interval", "Resend interval far from nominal", severity.NOTE)
seq("spurious_retransmission", "Retransmission after the acknowledgement", severity.NOTE)
seq("ack_without_command", "Acknowledgement without a matching command")
seq("duplicate_ack", "Duplicate acknowledgement", severity.NOTE)
seq("ack_late", "Command not acknowledged in time", severity.ERROR)
seq("never_acked", "Command never acknowledged in the capture", severity.ERROR)
seq("restart", "Sender restarted: serial counter started afresh")
seq("silent_until_end", "Periodic stream silent until the end of the capture (watchdog)", severity.ERROR)
seq("command_interrupted", "Command interrupted by its sender's restart", severity.NOTE)
seq("burst_missing", "VRPO burst: packet number missing", severity.WARN, group.REASSEMBLE)
seq("burst_incomplete", "Incomplete VRPO burst", severity.WARN, group.REASSEMBLE)
do
    local expert_list, expert_codes = {}, {}
    for code in pairs(E) do expert_codes[#expert_codes + 1] = code end
    table.sort(expert_codes) -- (a fixed order, as the fields)
    for i, code in ipairs(expert_codes) do expert_list[i] = E[code] end
    vm110.experts = expert_list
end

-- The stream analysis's findings, as Wireshark's TCP analysis shows its own: each in the Info
-- column in front ("[Serial Gap] VRPI ..."), all of a packet in vm110.analysis.flags (one filter
-- or colouring rule finds every packet with a finding), and its expert with a constant summary.
-- `false`: the marker depends on the packet type (retransmissions).
local FINDING = {
    serial_gap = "Serial Gap", serial_duplicate = "Duplicate", serial_out_of_order = "Out-Of-Order",
    restart = "Restart", watchdog_vrpi = "Watchdog", watchdog_vrpo = "Watchdog",
    silent_until_end = "Silent Until End", vrpo_interval = "VRPO Interval", time_backwards = "Time Backwards",
    retransmission = false, spurious_retransmission = false, resend_interval = "Resend Interval",
    ack_without_command = "Ack Without Command", duplicate_ack = "Duplicate Ack", ack_late = "Late Ack",
    never_acked = "Unacknowledged", command_interrupted = "Interrupted",
    burst_missing = "Burst Packet Missing", burst_incomplete = "Incomplete Burst",
}

-- A number preference outside the range the matching `vm110 analyze` option takes is refused as
-- analyze refuses it: read_settings() says so (report_failure: a dialog in Wireshark, a line on
-- tshark's standard error) and uses the default. (A duplicate window of 0 made every mirror copy a
-- restart; an input port above 65533 put the output port past 65535.)
local PREF_RANGES = {} -- { name, min, max, default }, in the order of the preferences
do
    local MS = 3600000 -- (analyze: above 0 and at most an hour)
    local function uint(name, label, default, blurb, min, max)
        vm110.prefs[name] = Pref.uint(label, default, blurb)
        PREF_RANGES[#PREF_RANGES + 1] = { name, min, max, default }
    end
    local variant_enum, order_enum = {}, { { "little", "Little-endian (TS-0006 2.1)", 1 }, { "big", "Big-endian", 2 } }
    for i, v in ipairs(CRC_VARIANTS) do variant_enum[i] = { v.name, v.label, i } end
    vm110.prefs.crc_variant = Pref.enum("CRC variant", 1, "CRC-32 variant the packets are checked with", variant_enum,
        false)
    vm110.prefs.crc_byte_order = Pref.enum("Stored CRC byte order", 1, "Byte order of the CRC trailer", order_enum,
        false)
    vm110.prefs.check_crc = Pref.bool("Validate the CRC", true, "Calculate the CRC of each packet and flag bad ones")
    uint("input_port", "Input UDP port", DEFAULT_INPUT_PORT,
        "UDP port of input packets; output packets use this port + 2 (TS-0006 2.2)", 1, 65535 - OUTPUT_PORT_OFFSET)
    vm110.prefs.heuristic = Pref.bool("Find EG-Link on other UDP ports", true,
        "Heuristic: a known packet ID with a size that matches the UDP length")
    vm110.prefs.analysis = Pref.bool("Analyse the streams", true,
        "Serial gaps, intervals and watchdogs, retransmissions and acknowledgements, VRPO reassembly")
    vm110.prefs.serial_scope = Pref.enum("Serial number scope", 1,
        "One counter per sender, or one per packet type per sender",
        { { "sender", "Per sender (all packet types)", 1 }, { "type", "Per packet type per sender", 2 } }, false)
    uint("dup_window_ms", "Duplicate window (ms)", RULES.dup_window_ms,
        "A serial received again within this is a duplicate; a late packet fills a gap opened within it", 1, MS)
    uint("reuse_gap_ms", "Command ID reuse gap (ms)", RULES.reuse_gap_ms,
        "The same command ID again after a longer silence starts a new command", 1, MS)
    uint("vrpi_watchdog_ms", "VRPI watchdog (ms)", VRPI_WATCHDOG_MS,
        "Error above this VRPI interval (a watchdog violation)", 1, MS)
    uint("vrpo_watchdog_ms", "VRPO watchdog (ms)", VRPO_WATCHDOG_MS,
        "Error above this VRPO interval (a watchdog violation)", 1, MS)
    uint("vrpo_min_ms", "VRPO recommended minimum interval (ms)", VRPO_PERIOD_MIN_MS, "Note below this", 1, MS)
    uint("vrpo_max_ms", "VRPO recommended maximum interval (ms)", VRPO_PERIOD_MAX_MS, "Note above this", 1, MS)
    uint("resend_ms", "Command resend interval (ms)", COMMAND_RESEND_MS, "Nominal resend interval", 1, MS)
    uint("resend_tolerance_ms", "Resend interval tolerance (ms)", COMMAND_RESEND_MS / 2,
        "Note when a resend interval differs from the nominal one by more than this", 0, MS)
    uint("vrci_fail_ms", "VRCI failure timeout (ms)", VRCI_FAIL_MS,
        "Acknowledgement later than this: failed", 1, MS)
    uint("vrco_give_up_ms", "VRCO give-up timeout (ms)", VRCO_GIVE_UP_MS,
        "Acknowledgement later than this: late", 1, MS)
    uint("vrpo_data_size", "Configured periodic data size (bytes)", 0,
        "Total VRPO periodic data of a burst; 0 = infer (a burst ends with a packet of fewer than 488 bytes, or its "
        .. "packets all carry 488 bytes and are at least as many as in the sender's longest complete such burst)",
        0, 65535)
    uint("vrpo_number_start", "First VRPO packet number", 0,
        "Packet number of a burst's first packet (0 or 1)", 0, 1)
    uint("burst_gap_ms", "VRPO burst gap (ms)", VRPO_BURST_GAP_MS,
        "A new burst starts after this gap (or after a complete burst)", 1, MS)
    vm110.prefs.machine = Pref.string("Machine", "",
        "Key of the machine-specific sub-dissectors in the vm110.periodic_data and vm110.command_data tables")
    vm110.prefs.fields_from_command_line = Pref.bool("tshark: only what the command line reads", true,
        "Wireshark 4.0's tshark -T fields builds every field of every packet; build only the vm110 fields its "
        .. "command line names (-e, -Y, -R, -z), as later versions do. A single-pass tshark whose output reads "
        .. "nothing of the stream analysis (no analysis field, column, tap or expert field) does not run it. "
        .. "Off: every field on 4.0, and the analysis always (say, for a Lua script of your own that reads "
        .. "vm110 fields or expert infos)")
    vm110.prefs.tune_gc = Pref.bool("Tune Lua's garbage collector", false,
        "Collector settings that make this dissector faster (Lua 5.4: generational; Lua 5.2: pause 100, "
        .. "step multiplier 800). They apply to every Lua plugin of this Wireshark, so they are off by default")
end

---------------------------------------------------------------------------------------------
-- 5. Tree and Info column
-- Every Lua tree item costs a TvbRange and a TreeItem userdata, even one Wireshark discards:
-- far more than a C dissector pays. So a visible tree (packet details, tshark -V/-O, PDML)
-- gets every field, with labels and subtrees; an invisible one (tshark -T fields, display
-- filters, the GUI's packet list, taps) only the fields something references
-- (TreeItem:referenced), flat under the protocol item. Experts are always added, on the
-- protocol item when their field is not built. Methods are fetched once (`item:add(...)`
-- looks the method up in C on every call).
---------------------------------------------------------------------------------------------
-- Preferences as plain values (read_settings()): reading vm110.prefs costs C calls on every packet.
-- single_pass: this is a single-pass tshark, where no frame is dissected twice and the tree's
-- visibility never changes (so that neither is asked per packet).
local settings = { single_pass = TSHARK_OPTIONS and TSHARK_OPTIONS.single_pass or false }
local tree_add, tree_add_le, set_generated = TreeItem.add, TreeItem.add_le, TreeItem.set_generated
local add_expert, append_text, tvb_range = TreeItem.add_proto_expert_info, TreeItem.append_text, Tvb.range
local referenced = TreeItem.referenced
-- The Wireshark calls made for every packet, as the C functions themselves: `pinfo.number` goes
-- through wslua's attribute dispatcher, which looks the getter up by name on every access (in the
-- class metatable's __getters, wslua's layout since 1.99; plain indexing where a Wireshark keeps
-- them elsewhere), and `tvb:raw()` looks the method up.
local WS = { raw = Tvb.raw, offset = Tvb.offset, number = false }
function WS.init(pinfo)
    local mt = getmetatable(pinfo)
    local getters = type(mt) == "table" and rawget(mt, "__getters")
    for _, name in ipairs({ "number", "abs_ts", "src_port", "src", "visited", "in_error_pkt", "fragmented" }) do
        local f = type(getters) == "table" and rawget(getters, name)
        WS[name] = type(f) == "function" and f or function(p) return p[name] end
    end
end

-- A view: field name -> true when it is built; `visible` for labels and subtrees; `layouts`:
-- per packet type, the payload layout entries that are built (made when first asked for: a
-- view of a visited dissection serves one packet).
local LAZY_LAYOUTS = {
    __index = function(layouts, id)
        local view, list = layouts.view, {}
        for _, f in ipairs(TYPES[id].layout) do
            if view[f[1]] then list[#list + 1] = f end
        end
        layouts[id] = list
        return list
    end,
}
-- `flat`: per packet type, a function(root, r, v) that adds the built fields of a packet with
-- nothing to flag on an invisible tree, straight-line code like the payload readers; false when
-- a bytes field is built (those take the general path, which gives them their bytes). Each field:
-- where 1 the record's r[key] (absent when false), 2 the payload value v[key], 3 the direction,
-- 4 es_relays_open (a boolean, always added).
local compile_flat
do
    local SOURCE = {
        "local x = r.%s if x then tree_add(root, f[%d], x) end",
        "local x = v.%s if x ~= nil then tree_add(root, f[%d], x) end",
        "tree_add(root, f[%d], r.info.direction)",
        "tree_add(root, f[%d], r.es_relays_open)",
    }
    function compile_flat(list)
        local lines, fields = { "local tree_add, f = ...", "return function(root, r, v)" }, {}
        for i, e in ipairs(list) do
            local where = e[2]
            fields[i] = e[1]
            local line = where <= 2 and fmt(SOURCE[where], e[3], i) or fmt(SOURCE[where], i)
            lines[#lines + 1] = "do " .. line .. " end"
        end
        lines[#lines + 1] = "end"
        return assert(load(concat(lines, "\n"), "=vm110 flat", "t", {}))(tree_add, fields)
    end
end
local LAZY_FLAT = {
    __index = function(flat, id)
        local view, list = flat.view, {}
        local function put(name, where, key)
            if view[name] then list[#list + 1] = { F[name], where, key or name } end
        end
        put("type", 1)
        put("direction", 3)
        for _, h in ipairs(HEADER) do put(h[1], 1) end
        for _, f in ipairs(TYPES[id].layout) do
            if view[f[1]] and f[3] == "b" then list = false break end
            put(f[1], 2)
        end
        if list and id == "VRPI" then put("es_relays_open", 4) end
        if list and id == "VRPO" and view.periodic_data then list = false end
        if list then
            put("crc", 1)
            put("crc_calculated", 1, "crc_calc")
            put("crc_status", 1)
        end
        local adder = list and compile_flat(list)
        flat[id] = adder
        return adder
    end,
}
local function with_layouts(view)
    view.layouts = setmetatable({ view = view }, LAZY_LAYOUTS)
    view.flat = setmetatable({ view = view }, LAZY_FLAT)
    return view
end

-- `any`: some field is built; `columns`: the Info column is written (not by tshark -T fields).
local function every_view(columns)
    local view = { visible = true, any = true, columns = columns }
    for name in pairs(F) do view[name] = true end
    return with_layouts(view)
end
local EVERY, EVERY_NO_COLUMNS = every_view(true), every_view(false)
local NOTHING = with_layouts({ visible = false, any = false, columns = true })
local vm110_handle -- (the dissector handle, once registered: referenced when any vm110 field is)

-- The view of the fields a tree references. Made once per set of fields and kept: a visited
-- frame asks per packet (tshark -2's second pass, the GUI), and a new view there would compile
-- its flat adders again for every packet. The cache is a trie over the field list's indexes of
-- the referenced fields, so that finding a view allocates nothing.
local FIELD_LIST = {}
for name, f in pairs(F) do FIELD_LIST[#FIELD_LIST + 1] = { name, f } end
table.sort(FIELD_LIST, function(a, b) return a[1] < b[1] end)
local referenced_views = { [true] = {}, [false] = {} }
local function referenced_view(tree, columns)
    local node = referenced_views[columns]
    for i = 1, #FIELD_LIST do
        if referenced(tree, FIELD_LIST[i][2]) then
            local next_ = node[i]
            if not next_ then
                next_ = {}
                node[i] = next_
            end
            node = next_
        end
    end
    local view = node.view
    if not view then
        view = { visible = false, any = false, columns = columns }
        for i = 1, #FIELD_LIST do
            if referenced(tree, FIELD_LIST[i][2]) then view[FIELD_LIST[i][1]], view.any = true, true end
        end
        view = with_layouts(view)
        node.view = view
    end
    return view
end

-- Wireshark 4.0's `tshark -T fields` dissects with a visible tree (4.2 and later do not), so
-- referenced() says yes to every field, and every field would be built with its bytes and label
-- for output that prints a few values. There, the fields named on tshark's command line (-e,
-- -Y, -R, -z, -o; read from /proc/self/cmdline, so Linux only) are what is referenced, as a
-- later tshark works out by itself. Not where a display filter macro (${...}) could name more,
-- nor with --color, whose colouring rules (frame.coloring_rule.name) test fields the command line
-- does not name; the preference vm110.fields_from_command_line turns it off (for a Lua script of
-- your own that reads vm110 fields with Field.new under tshark 4.0 -T fields).
-- Returns the view, or nil when this is not such a command line.
local function command_line_view()
    local opts = TSHARK_OPTIONS
    if not opts or opts.T ~= "fields" or opts.V or opts.O or opts.P or opts.x then return nil end -- (details printed)
    local words = opts.words
    if words:find("${", 1, true) or words:find(" --color ", 1, true) then return nil end
    local view = { visible = false, any = false, columns = false }
    for name, f in pairs(F) do
        local abbr = tostring(f):match("(%S+) ftypes%.")
        -- (a whole name: vm110.crc is not vm110.crc.status)
        if abbr and words:find("[^%w_.]" .. abbr:gsub("%.", "%%.") .. "[^%w_.]") then
            view[name], view.any = true, true
        end
    end
    return with_layouts(view)
end

-- What is referenced changes only when Wireshark primes other fields (a new display filter,
-- column, tap, or tshark's second pass), and it then dissects frames again (pinfo.visited):
-- so one view serves a run of first-pass dissections, and visited ones ask per packet (about 90
-- referenced() calls: some 8 us a packet), but in tshark, whose second pass primes every frame
-- alike (its display filter, columns, -e fields and taps): one view serves that pass too.
local first_pass_view = false
local second_pass_view = false -- (tshark -2's, with an invisible tree)
local want = EVERY -- the view of the packet being dissected
local cmdline_view = false -- command_line_view(), once asked: a view, or nil

-- A visible tree: every field, unless this is tshark 4.0 -T fields (see command_line_view()).
-- Without column data (tshark -T fields without _ws.col) a column reads "(info)".
local function visible_view(pinfo)
    if tostring(pinfo.cols.info) ~= "(info)" then return EVERY end
    if cmdline_view == false then
        cmdline_view = settings.fields_from_command_line and command_line_view() or nil
    end
    return cmdline_view or EVERY_NO_COLUMNS
end

-- The stream analysis has readers only in what a run prints or filters. A single-pass tshark
-- dissects each frame once and prints it before reading the next, so a run that reads none of
-- it has no use for any of it, now or later: no analysis field referenced (-e, -Y, -R, a Lua
-- Field.new, which 4.2+ primes), no columns (whose Info carries its markers), no tree printed, no
-- tap (-z: expert infos, the statistics), no expert or colouring field named, and no machine
-- sub-dissector (it gets the reassembled data). `tshark -T fields -e vm110.serial` is such a run.
-- Expert infos a Lua script of the user's reads (Field.new of _ws.expert, an expert tap) cannot be
-- seen from here: the preference vm110.fields_from_command_line off runs the analysis always.
local choose_view
do
    local ANALYSIS = {}
    for name, f in pairs(F) do
        local abbr = tostring(f):match("(%S+) ftypes%.")
        if abbr and (abbr:find("^vm110%.analysis%.") or abbr:find("^vm110%.burst%.")
                or abbr == "vm110.reassembled") then
            ANALYSIS[#ANALYSIS + 1] = name
        end
    end
    local function unread(view)
        local opts = TSHARK_OPTIONS
        if not settings.single_pass or not settings.fields_from_command_line or view.visible or view.columns
            or settings.machine ~= "" or opts.z then
            return false
        end
        local words = opts.words
        -- (expert infos as fields, colouring rules, and 4.0's protocol item, whose label takes markers)
        for _, word in ipairs({ "_ws.expert", "vm110.expert", "coloring", "--color", " vm110 ", "${" }) do
            if words:find(word, 1, true) then return false end
        end
        for _, name in ipairs(ANALYSIS) do
            if view[name] then return false end
        end
        return true
    end

    function choose_view(tree, pinfo, visited)
        if settings.single_pass and first_pass_view then return first_pass_view end
        local visible = tree.visible
        if visited then
            first_pass_view = false
            if visible then return visible_view(pinfo) end
            if second_pass_view then return second_pass_view end
            local view = referenced(tree, vm110_handle) and referenced_view(tree, true) or NOTHING
            if TSHARK_OPTIONS then second_pass_view = view end
            return view
        end
        if not first_pass_view or first_pass_view.tree_visible ~= visible then
            first_pass_view = visible and visible_view(pinfo)
                or referenced_view(tree, tostring(pinfo.cols.info) ~= "(info)")
            first_pass_view.tree_visible = visible
            settings.analysing = settings.analysis and not unread(first_pass_view)
        end
        return first_pass_view
    end
end

-- TvbRanges of the packet being dissected, by offset and length: a field and the generated
-- fields derived from it share one (each is a userdata the collector must finalise). Header and
-- payload fields, which nothing derives from, take Tvb.range directly.
local ranges, range_owner, dissection = {}, {}, 0
local function range(tvb, off, len)
    local k = off * 65536 + len
    if range_owner[k] == dissection then return ranges[k] end
    local r = tvb_range(tvb, off, len)
    ranges[k], range_owner[k] = r, dissection
    return r
end

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
    local v, id = r.values, r.type
    local text
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
    if r.problems ~= EMPTY then
        local p = {}
        for _, code in ipairs(PROBLEM_ORDER) do
            if r.problems[code] then p[#p + 1] = PROBLEM_TEXT[code] end
        end
        text = text .. " [Illegal: " .. concat(p, ", ") .. "]"
    end
    return text
end

-- A field warning's summary names the field first and no value (Wireshark's expert statistics
-- group by summary: one line per field and code; the value is the field's).
local function field_message(code, name)
    if code == "out_of_range" then
        local low_high = FIELDS[name].range
        return fmt("vm110.%s is outside %d..%d", name, low_high[1], low_high[2])
    elseif code == "unknown_enum" then
        return fmt("vm110.%s is not a defined value", name)
    elseif code == "disarmed_ru_data" then
        return fmt("vm110.%s is not zero while vm110.armed_ru = 0", name)
    elseif code == "origin_nonzero" then
        return fmt("vm110.%s should be 0 on output packets", name)
    end
    return fmt("vm110.%s should be 0", name)
end

local function field_experts(r, item, name)
    local codes = r.fieldwarn[name]
    if codes then
        for _, code in ipairs(codes) do add_expert(item, E[code], field_message(code, name)) end
    end
end

-- Bytes no field owns; returns the item, or nil when there are none or it is not built.
local function add_undecoded(tree, tvb, off, len, why)
    if len <= 0 or not want.undecoded then return end
    local item = tree_add(tree, F.undecoded, range(tvb, off, len))
    if want.visible then append_text(item, " (" .. why .. ")") end
    return item
end

-- A generated field when it is built; else the parent, which then carries the field's experts.
-- On an invisible tree an item is its value alone: its bytes and the generated mark are shown
-- only in a visible one, and a TvbRange per item is the largest cost of a Lua field.
local function generated(parent, name, tvb, off, len, value)
    if not want[name] then return parent end
    if not want.visible then return tree_add(parent, F[name], value) end
    local item = tree_add(parent, F[name], range(tvb, off, len), value)
    set_generated(item)
    return item
end

local function add_header(r, tvb, root)
    local n, visible = r.n, want.visible
    if r.type then
        local info = r.info
        local item = root
        if visible then
            local label = info and info.label or fmt("Packet ID: %s (Unknown)", printable(r.type))
            item = tree_add(root, F.type, range(tvb, 0, ID_LEN), r.type, label)
        elseif want.type then
            item = tree_add(root, F.type, r.type)
        end
        if info then
            generated(item, "direction", tvb, 0, ID_LEN, info.direction)
        elseif not r.cut then -- (cut short: truncated, and for that alone, as decode() says)
            add_expert(item, E.unknown_id)
        end
    else
        add_undecoded(root, tvb, 0, n, "shorter than a packet ID")
    end
    if n <= ID_LEN then return end
    local hlen = n < PREFIX_LEN and n - ID_LEN or HEADER_LEN
    local header = visible and tree_add(root, range(tvb, ID_LEN, hlen), "Header") or root
    local off = ID_LEN
    for _, h in ipairs(HEADER) do
        local name = h[1]
        local value = r[name]
        if not value then break end
        local item = header
        if want[name] and visible then
            item = tree_add_le(header, F[name], tvb_range(tvb, h.off, h[2]))
        elseif want[name] then
            item = tree_add(header, F[name], value)
        end
        field_experts(r, item, name)
        if name == "revision" and r.problems.revision then
            add_expert(item, E.revision)
        elseif name == "size" then
            if r.problems.size_mismatch then
                add_expert(item, E.size_mismatch) -- (the numbers: vm110.size, udp.length)
            end
            if r.problems.size_too_large then
                add_expert(item, E.size_too_large)
            end
        end
        off = h.off + h[2]
    end
    add_undecoded(header, tvb, off, ID_LEN + hlen - off, "header cut short")
end

local function add_relays(r, tvb, parent)
    local item = generated(parent, "es_relays_open", tvb, PREFIX_LEN, 1, r.es_relays_open)
    if r.es_relays_open then
        add_expert(item, E.es_relays_open)
    end
end

local function add_payload(r, tvb, root)
    local info, v, fieldwarn = r.info, r.values, r.fieldwarn
    local plen = r.pay_end - PREFIX_LEN
    local payload = root
    if want.visible then
        payload = tree_add(root, range(tvb, PREFIX_LEN, plen), info.payload_labels[plen])
    end
    local whole = r.present == info.layout
    local relays = v.bu_state ~= nil
    local visible = want.visible
    for _, f in ipairs(whole and want.layouts[r.type] or r.present) do
        local name = f[1]
        if whole or want[name] then
            local item
            if visible or f[3] == "b" then
                item = tree_add_le(payload, F[name], tvb_range(tvb, f.off, f[2]))
            else
                item = tree_add(payload, F[name], v[name])
            end
            if fieldwarn[name] then
                field_experts(r, item, name)
                fieldwarn[name] = nil -- shown
            end
            if name == "bu_state" then -- (es_relays_open right below the state it is derived from)
                add_relays(r, tvb, payload)
                relays = false
            end
        end
    end
    for name in pairs(fieldwarn) do -- warnings of fields not built (header fields: shown already)
        if v[name] ~= nil then field_experts(r, payload, name) end
    end
    if relays then add_relays(r, tvb, payload) end
    local off = r.decoded_end
    if r.data_len and want.periodic_data then
        tree_add(payload, F.periodic_data, range(tvb, off - r.data_len, r.data_len))
    end
    if r.problems.truncated then
        add_expert(payload, E.truncated, "Truncated: payload shorter than the packet type's layout")
        add_undecoded(payload, tvb, off, r.pay_end - off, "part of a field")
    elseif r.extra then
        local item = add_undecoded(payload, tvb, off, r.pay_end - off, "beyond the layout") or payload
        add_expert(item, E.extra_payload) -- (the bytes: vm110.undecoded)
    end
end

local CRC_VERDICT = { [CRC_BAD] = " [incorrect]", [CRC_GOOD] = " [correct]", [CRC_UNVERIFIED] = " [unverified]" }

local function add_crc(r, tvb, root)
    local item = root
    if want.visible then
        item = tree_add(root, F.crc, range(tvb, r.crc_off, CRC_LEN), r.crc,
            fmt("CRC: 0x%08x%s", r.crc, CRC_VERDICT[r.crc_status]))
    elseif want.crc then
        item = tree_add(root, F.crc, r.crc)
    end
    if r.crc_calc then generated(item, "crc_calculated", tvb, r.crc_off, CRC_LEN, r.crc_calc) end
    generated(item, "crc_status", tvb, r.crc_off, CRC_LEN, r.crc_status)
    if r.crc_status == CRC_BAD then
        add_expert(item, E.bad_crc) -- (the numbers: vm110.crc, vm110.crc.calculated)
    end
end

-- The usual packet on an invisible tree (decoded whole, nothing to flag): its built fields'
-- values, flat under the protocol item. False when a bytes field is built.
local function add_flat(r, root)
    local adder = want.flat[r.type]
    if not adder then return false end
    adder(root, r, r.values)
    return true
end

-- A datagram cut short (decode()'s `cut`): the undecoded bytes' label, the expert's message.
local CUT_SHORT = {
    snaplen = { "cut short by the capture", "Truncated: cut short by the capture (snaplen)" },
    fragment = { "cut short: an IP fragment", "Truncated: the first IP fragment of a datagram not reassembled" },
    quote = { "cut short by an ICMP error's quote", "Truncated: cut short by an ICMP error's quote" },
}
local function add_tree(r, tvb, tree)
    local root
    if want.visible then
        root = tree_add(tree, vm110, range(tvb, 0, r.n), "VM-110 EG-Link, " .. r.info_text)
    else
        root = tree_add(tree, vm110) -- (no bytes: see generated())
    end
    local clean = r.problems == EMPTY and r.fieldwarn == EMPTY and not r.es_relays_open and not r.extra
    if not want.any and clean then return root end -- nothing referenced, nothing to flag
    if clean and not want.visible and r.payload and add_flat(r, root) then return root end
    add_header(r, tvb, root)
    local n = r.n
    if n < PREFIX_LEN and not r.cut then
        add_expert(root, E.truncated, "Truncated: shorter than the 16-byte packet ID and header")
        return root
    end
    if r.cut then
        local item = add_undecoded(root, tvb, PREFIX_LEN, n - PREFIX_LEN, CUT_SHORT[r.cut][1]) or root
        add_expert(item, E.truncated, CUT_SHORT[r.cut][2])
        return root
    end
    if not r.crc_off then
        local item = add_undecoded(root, tvb, PREFIX_LEN, n - PREFIX_LEN, "no room for a CRC") or root
        add_expert(item, E.truncated, "Truncated: no room for a CRC")
        return root
    end
    if r.payload then
        add_payload(r, tvb, root)
    else
        add_undecoded(root, tvb, PREFIX_LEN, r.crc_off - PREFIX_LEN, "payload not decoded")
    end
    add_crc(r, tvb, root)
    add_undecoded(root, tvb, r.crc_off + CRC_LEN, n - r.crc_off - CRC_LEN, "after the CRC")
    return root
end

---------------------------------------------------------------------------------------------
-- 6. Dissector, registration
---------------------------------------------------------------------------------------------
-- The collector of Wireshark's Lua state is every Lua plugin's: left as Wireshark sets it, unless
-- the preference vm110.tune_gc (off by default) asks for the settings `make bench` can measure
-- (generational on Lua 5.4; on 5.2 collecting continuously, pause 100, with larger steps);
-- turning it off again restores what was there before.
local tune_collector
do
    local saved = false -- what was there before: {mode} on Lua 5.4, {pause, stepmul} on 5.2
    function tune_collector(on)
        if on and not saved then
            if _VERSION >= "Lua 5.4" then
                saved = { collectgarbage("generational") }
            else
                saved = { collectgarbage("setpause", 100), collectgarbage("setstepmul", 800) }
            end
        elseif not on and saved then
            if _VERSION >= "Lua 5.4" then
                collectgarbage(saved[1])
            else
                collectgarbage("setpause", saved[1])
                collectgarbage("setstepmul", saved[2])
            end
            saved = false
        end
    end
end

-- (settings: the preferences as plain values, above)
local function read_settings()
    local prefs = setmetatable({}, { __index = vm110.prefs }) -- (the values refused replaced)
    -- A refused value goes back to the default in Wireshark's own preferences too (reset_preference,
    -- Wireshark 3.5 and later), so that the preferences dialog shows the value used and the next save
    -- of the preferences does not write the refused one again (it stayed in the file, refused anew on
    -- every start).
    local function reset_refused(name)
        if reset_preference then reset_preference("vm110." .. name) end
    end
    local refused = {}
    for _, r in ipairs(PREF_RANGES) do
        local name, min, max, default = r[1], r[2], r[3], r[4]
        local value = prefs[name]
        if value < min or value > max then
            refused[#refused + 1] = fmt("vm110.%s = %d is outside %d to %d; %d is used", name, value, min, max,
                default)
            prefs[name] = default
            reset_refused(name)
        end
    end
    if prefs.vrpo_min_ms > prefs.vrpo_max_ms then -- (analyze: --vrpo-range MIN at most MAX)
        refused[#refused + 1] = fmt("vm110.vrpo_min_ms = %d is above vm110.vrpo_max_ms = %d; %d and %d are used",
            prefs.vrpo_min_ms, prefs.vrpo_max_ms, VRPO_PERIOD_MIN_MS, VRPO_PERIOD_MAX_MS)
        prefs.vrpo_min_ms, prefs.vrpo_max_ms = VRPO_PERIOD_MIN_MS, VRPO_PERIOD_MAX_MS
        reset_refused("vrpo_min_ms")
        reset_refused("vrpo_max_ms")
    end
    -- (said once: Wireshark applies the preferences more than once, tshark once per -o)
    local text = concat(refused, "\nvm110: preference ")
    if text ~= "" and text ~= settings.refused then report_failure("vm110: preference " .. text) end
    settings.refused = text
    settings.variant = prefs.check_crc and CRC_VARIANTS[prefs.crc_variant] or nil
    settings.big_endian = prefs.crc_byte_order == 2
    settings.heuristic = prefs.heuristic
    settings.analysis = prefs.analysis
    settings.analysing = prefs.analysis -- (and something reads it: choose_view())
    settings.per_type = prefs.serial_scope == 2
    settings.dup_window, settings.reuse_gap = prefs.dup_window_ms, prefs.reuse_gap_ms
    settings.vrpi_watchdog, settings.vrpo_watchdog = prefs.vrpi_watchdog_ms, prefs.vrpo_watchdog_ms
    settings.vrpo_min, settings.vrpo_max = prefs.vrpo_min_ms, prefs.vrpo_max_ms
    settings.resend, settings.resend_tolerance = prefs.resend_ms, prefs.resend_tolerance_ms
    settings.vrci_fail, settings.vrco_give_up = prefs.vrci_fail_ms, prefs.vrco_give_up_ms
    settings.data_size, settings.number_start = prefs.vrpo_data_size, prefs.vrpo_number_start
    settings.burst_gap, settings.machine = prefs.burst_gap_ms, prefs.machine
    settings.fields_from_command_line = prefs.fields_from_command_line
    settings.input_port = prefs.input_port
    tune_collector(prefs.tune_gc)
end

-- Per-frame memos, by frame number and offset (a frame may carry more than one EG-Link packet:
-- one quoted in an ICMP error, say). Per chunk of 256 frames one array, preallocated: [2i + 1]
-- the offset of frame i's first EG-Link packet, [2i + 2] its value; further packets of a frame
-- go to `more`. Array slots cost no hashing; small chunks matter because the collector traverses
-- a table again whenever a new object is stored in it.
local CHUNK_FRAMES = 256
local new_chunk = assert(load("return {" .. string.rep("false,", 2 * CHUNK_FRAMES) .. "}", "=vm110 chunk", "t", {}))
local function new_memo()
    return { more = {} }
end
local function memo_get(memo, number, offset)
    local i = number % CHUNK_FRAMES
    local chunk = memo[number - i]
    if chunk and chunk[2 * i + 1] == offset then return chunk[2 * i + 2] end
    return memo.more[number * 0x10000 + offset]
end
local function memo_set(memo, number, offset, value)
    local i = number % CHUNK_FRAMES
    local chunk = memo[number - i]
    if not chunk then
        chunk = new_chunk()
        memo[number - i] = chunk
    end
    local owner = chunk[2 * i + 1]
    if owner == false or owner == offset then
        chunk[2 * i + 1], chunk[2 * i + 2] = offset, value
    else
        memo.more[number * 0x10000 + offset] = value
    end
end

-- Calculated CRC per frame: re-dissection (GUI clicks, second pass) skips the CRC. Emptied when
-- a capture is (re)loaded and when the preferences change.
local crc_memo = new_memo()

---------------------------------------------------------------------------------------------
-- Stream analysis (docs/rules.md: the rules of interpretation.md, precisely)
-- Computed once per packet, on the first pass in capture order (pinfo.visited false), into a
-- per-frame result: a number for most packets (the interval, -1 for none), else a table of
-- numbers plus references to shared command, burst and restart records. Every later dissection
-- (GUI clicks in any order, tshark -2) only reads them. Facts that depend on later packets (a
-- restart candidate confirmed or not by its counter's next packet, a command interrupted by a
-- restart or never acknowledged, an incomplete burst, a stream silent until the end) are final
-- once the whole capture has been seen: finalize() runs before the first visited dissection,
-- and they are shown on visited passes only. Illegal packets are not analysed (not received), nor
-- is a datagram quoted in an ICMP error.
-- All state is rebuilt in init().
---------------------------------------------------------------------------------------------
local results = new_memo() -- frame -> analysis of that packet (false: not analysed)
local senders = {}      -- (origin, port, direction) -> source address -> sender
local sender_list = {}  -- the same, in order of first appearance (statistics, end of capture)
local hosts = {}        -- "direction origin address" -> that host's senders on any port (new-port restarts)
local counters = {}     -- sender -> serial counter (per-type scope: sender -> type -> counter)
local by_id = {}        -- command kind -> command ID -> its commands (any sender), in the order they began
-- Command events (and restarts) wait here, in capture order, while a restart candidate before
-- them is undecided and not released: a restart interrupts its sender's commands as of the
-- candidate's time.
local queue, qhead, qtail = {}, 1, 0
-- The capture so far: its last record (any frame: number, time), the analysis clock (rules.md:
-- the latest time of a legal packet), and the restart candidates not yet released, a list from the
-- oldest (`waiting`, linked by `next_waiting`) to the newest (`waiting_last`), made in clock order:
-- one still undecided when the clock reaches RULES.candidate_wait_ms after it is released (the
-- queue runs past it as no restart; its counter still decides it), so a sender silent for good
-- after one holds the queue no longer. (Fields: the main chunk's locals are limited to 200.)
local capture = { number = 0, last = false, clock = -math.huge, waiting = false, waiting_last = false }
local dirty = false     -- packets analysed since the last finalize()
local silent_marks = {} -- results finalize() marked silent until the end

local DUPLICATE, LATE, CANDIDATE = -1, -2, -3
local DUP_RES = { serial = DUPLICATE } -- every duplicate's result: it takes no further part

local function reset_analysis()
    results, senders, sender_list, hosts, counters = new_memo(), {}, {}, {}, {}
    by_id = { VRCI = {}, VRCO = {} }
    queue, qhead, qtail = {}, 1, 0
    capture = { number = 0, last = false, clock = -math.huge, waiting = false, waiting_last = false }
    dirty, silent_marks = false, {}
end
reset_analysis()

-- Frame `n` at time `t` was seen on the first pass: the capture's last record, if the latest.
local function note_record(n, t)
    if n > capture.number then capture.number, capture.last = n, t end
end

-- Seconds to milliseconds, rounded to the microsecond: capture times are doubles of the epoch,
-- whose last bits are noise; pcap timestamps are (at most) microseconds in practice.
local function ms(seconds)
    local us = seconds * 1e6 + 0.5
    return (us - us % 1) / 1000 -- (floor without a call)
end

local function timeout_of(cmd)
    return cmd.type == "VRCI" and settings.vrci_fail or settings.vrco_give_up
end

-- Commands (rules.md "Commands"): a command is (kind, sender, command ID); a sender may have any
-- number open. `snd.open`: its commands that a restart could still interrupt; `snd.epoch` counts
-- its restarts (a command ID after one starts a new command).
local function interrupt(snd, t, frame)
    local open = snd.open
    for i = 1, #open do
        local cmd = open[i]
        if not cmd.ack and not cmd.interrupted and ms(t - cmd.t1) <= timeout_of(cmd) then
            cmd.interrupted = frame
            snd.interrupted = snd.interrupted + 1
        end
    end
    snd.open = {}
    snd.epoch = snd.epoch + 1
end

local function run_command(kind, cid, snd, t, frame, res)
    local target = ACK_OF[kind]
    if not target then
        local mine = snd.cmds[kind]
        local cmd = mine[cid]
        if cmd and cmd.epoch == snd.epoch and ms(t - cmd.tlast) < settings.reuse_gap then
            res.cmd, res.number = cmd, cmd.n -- a retransmission (duplicates never get here)
            res.since, res.resend = ms(t - cmd.t1), ms(t - cmd.tlast)
            res.spurious = cmd.ack and true or false
            cmd.n, cmd.tlast = cmd.n + 1, t
            snd.retransmissions = snd.retransmissions + 1
            return
        end
        cmd = { id = cid, type = kind, sender = snd, frame = frame, t1 = t, tlast = t, n = 1, ack = false,
            ack_ms = false, epoch = snd.epoch, interrupted = false }
        mine[cid] = cmd -- (a new ID ends nothing)
        local list = by_id[kind][cid]
        if list then list[#list + 1] = cmd else by_id[kind][cid] = { cmd } end
        local open = snd.open
        if #open >= 64 then -- keep only those a restart could still interrupt
            local keep = {}
            for i = 1, #open do
                local c = open[i]
                if not c.ack and ms(t - c.t1) <= timeout_of(c) then keep[#keep + 1] = c end
            end
            open = keep
            snd.open = keep
        end
        open[#open + 1] = cmd
        snd.commands = snd.commands + 1
        res.cmd, res.number = cmd, 0
        return
    end
    -- An acknowledgement: of the command with this ID (any sender, not interrupted) that began last.
    local best, list = false, by_id[target][cid]
    if list then
        for i = #list, 1, -1 do
            if not list[i].interrupted then
                best = list[i]
                break
            end
        end
    end
    res.ack_of = best
    if not best then return end
    res.ack_ms = ms(t - best.t1)
    if best.ack then
        res.duplicate_ack = true
    else
        best.ack, best.ack_ms = frame, res.ack_ms
        best.sender.acked = best.sender.acked + 1
        res.ack_last_ms = ms(t - best.tlast)
    end
end

-- Runs the queue up to the first restart candidate neither decided nor released. A released one
-- runs as no restart: expire() runs the queue past it at once (the candidates before it in the
-- queue are older, released or decided too), so it changes no command even if confirmed later.
local function flush()
    while qhead <= qtail do
        local ev = queue[qhead]
        local rec = ev.restart
        if rec then
            if not (rec.decided or rec.released) then return end
            if rec.confirmed then interrupt(rec.of, rec.t, rec.frame) end
        else
            run_command(ev.kind, ev.cid, ev.snd, ev.t, ev.frame, ev.res)
        end
        queue[qhead] = nil
        qhead = qhead + 1
    end
    qhead, qtail = 1, 0
end

local function command_event(kind, cid, snd, t, frame, res)
    if qtail < qhead then return run_command(kind, cid, snd, t, frame, res) end
    qtail = qtail + 1
    queue[qtail] = { kind = kind, cid = cid, snd = snd, t = t, frame = frame, res = res }
end

local function restart_event(rec)
    if qtail < qhead and rec.decided then return interrupt(rec.of, rec.t, rec.frame) end
    qtail = qtail + 1
    queue[qtail] = { restart = rec }
end

-- Serial counters (rules.md "Serial numbers"): h, the start (first packet or last restart), the
-- time each serial was last accepted (`acc`, by serial), the open gaps (ranges {first serial,
-- count, time opened, the result of the packet that opened it}, oldest first; a late packet
-- counts itself in that result's `filled`), the previous accepted packet's time (`prev`), and the
-- accepted times of the last RATE_WINDOW_S seconds in a ring (the rate of the plausible-gap
-- test, counted exactly: by binary search while the times are in order).
local new_counter, classify, expire
do
    local RATE_WINDOW_S, CONFIRM_SPAN, WAIT_MS = RULES.rate_window_s, RULES.confirm_span, RULES.candidate_wait_ms
    local GAP_SLACK, GAP_RATE_FACTOR, GAP_MIN_RATE = RULES.gap_slack, RULES.gap_rate_factor, RULES.gap_min_rate

    function new_counter(snd, s, t)
        return { snd = snd, h = s, start = t, prev = t, acc = { [s] = t }, gaps = {}, lost = 0, wraps = 0,
            ring = { t }, rhead = 1, rtail = 1, cand = false }
    end

    local function accept(c, s, t)
        c.acc[s], c.prev = t, t
        local ring, tail = c.ring, c.rtail + 1
        ring[tail], c.rtail = t, tail
        local head, lo = c.rhead, t - RATE_WINDOW_S
        if ring[head] < lo then
            repeat
                ring[head] = nil
                head = head + 1
            until ring[head] >= lo
            if head > 32 and head + head > tail then -- (keeps the ring in the table's array part)
                local n = tail - head + 1
                for i = 1, n do ring[i] = ring[head + i - 1] end
                for i = n + 1, tail do ring[i] = nil end
                head, c.rtail = 1, n
            end
            c.rhead = head
        end
    end

    -- First ring index from `a` with a time >= v (the counter's clock: times in order).
    local function lower_bound(ring, a, b, v)
        while a < b do
            local m = (a + b - (a + b) % 2) / 2
            if ring[m] < v then a = m + 1 else b = m end
        end
        return a
    end

    -- d - 1 <= 64 + 4 max(r, 20) dt: r = accepted packets in [t - W, t) / W, W = min(10 s, t - start).
    local function plausible(c, d, t)
        local w, lo = t - c.start, c.start
        if w > RATE_WINDOW_S then w, lo = RATE_WINDOW_S, t - RATE_WINDOW_S end
        local rate = 0
        if w > 0 then
            local ring, head, tail = c.ring, c.rhead, c.rtail
            rate = (lower_bound(ring, head, tail + 1, t) - lower_bound(ring, head, tail + 1, lo)) / w
        end
        if rate < GAP_MIN_RATE then rate = GAP_MIN_RATE end
        return d - 1 <= GAP_SLACK + GAP_RATE_FACTOR * rate * (t - c.prev)
    end

    -- A candidate decided: confirmed, the counter starts afresh at it (a restart, counted even when
    -- released: flush() skips its command effect); else it stays out of order.
    local function decide(c, confirmed)
        local rec, snd = c.cand, c.snd
        c.cand, rec.decided = false, true
        if confirmed then
            rec.confirmed = true
            local s, t = rec.to, rec.t
            c.h, c.start, c.prev, c.acc, c.gaps = s, t, t, { [s] = t }, {}
            c.ring, c.rhead, c.rtail = { t }, 1, 1
            snd.restarts[#snd.restarts + 1] = rec
        else
            snd.late = snd.late + 1
        end
        flush()
    end

    -- The waiting candidates made WAIT_MS or more before the analysis clock `now` leave the list,
    -- those their counters have not decided released, and the queue runs past them. `now` false:
    -- the capture's end, every candidate still pending is out of order.
    function expire(now)
        if not now then
            for _, snd in ipairs(sender_list) do
                for _, c in ipairs(snd.states) do
                    if c.cand then decide(c, false) end
                end
            end
            capture.waiting, capture.waiting_last = false, false
            return
        end
        local first = capture.waiting
        local rec = first
        while rec and ms(now - rec.t) >= WAIT_MS do
            if not rec.decided then rec.released = true end
            rec = rec.next_waiting
        end
        if rec == first then return end
        capture.waiting = rec
        if not rec then capture.waiting_last = false end
        flush()
    end

    -- Rules 1-5 for serial s at time t: returns the serials missing before it (>= 0), DUPLICATE,
    -- LATE or CANDIDATE. A candidate pending on the counter is decided first by the first packet
    -- with another serial, whenever it comes (copies of it are duplicates, whenever they come).
    function classify(c, s, t)
        local cand = c.cand
        if cand then
            if s == cand.to then return DUPLICATE end
            decide(c, (s - cand.to) % SERIAL_MODULUS <= CONFIRM_SPAN)
        end
        local ta = c.acc[s]
        if ta and ms(t - ta) < settings.dup_window then return DUPLICATE end
        local h = c.h
        local d = (s - h) % SERIAL_MODULUS
        if d == 1 then
            if s == 0 then c.wraps = c.wraps + 1 end
            c.h = s
            accept(c, s, t)
            return 0
        end
        local gaps = c.gaps
        if gaps[1] then
            local window = settings.dup_window
            while gaps[1] and ms(t - gaps[1][3]) >= window do table.remove(gaps, 1) end -- (lost for good)
            for i = #gaps, 1, -1 do
                local g = gaps[i]
                local k = (s - g[1]) % SERIAL_MODULUS
                if k < g[2] and ms(t - g[3]) < window then
                    local opener = g[4]
                    opener.filled = (opener.filled or 0) + 1
                    if g[2] == 1 then
                        table.remove(gaps, i)
                    elseif k == 0 then
                        g[1], g[2] = (s + 1) % SERIAL_MODULUS, g[2] - 1
                    elseif k == g[2] - 1 then
                        g[2] = k
                    else
                        table.insert(gaps, i + 1, { (s + 1) % SERIAL_MODULUS, g[2] - k - 1, g[3], opener })
                        g[2] = k
                    end
                    c.lost = c.lost - 1
                    accept(c, s, t)
                    return LATE
                end
            end
        end
        if d > 1 and d < SERIAL_HALF and plausible(c, d, t) then
            gaps[#gaps + 1] = { (h + 1) % SERIAL_MODULUS, d - 1, t }
            c.lost = c.lost + d - 1
            if s < h then c.wraps = c.wraps + 1 end
            c.h = s
            accept(c, s, t)
            return d - 1
        end
        accept(c, s, t) -- (moves nothing)
        return CANDIDATE
    end
end

-- Numbered: start, start+1, ... each once (in any order), every packet but the last by number
-- carrying 488 bytes. Ended: numbered, and the last fewer (or the data add up to the configured
-- size). Complete: ended; or (size inferred) all carry 488 and the sender sent no shorter packet
-- and no longer complete burst of full packets before (`need`: the least number of packets, taken
-- when the burst began; docs/rules.md, "VRPO bursts").
-- Kept as the burst grows, in constant time per packet (a burst may be endless): `bad` (a number
-- below the start or seen before), `top` (the highest number), `top_size` (its data length),
-- `short` (packets with fewer than 488 bytes). The numbers n distinct ones from `start` with the
-- highest start + n - 1 are exactly start ... start + n - 1.
local burst = {} -- (functions in a table: the main chunk's locals are limited to 200)
function burst.part(b, number, size)
    local seen = b.seen
    if number < settings.number_start or seen[number] then b.bad = true end
    seen[number] = true
    if number > b.top then b.top, b.top_size = number, size end
    if size ~= VRPO_MAX_DATA then b.short = b.short + 1 end
end

function burst.numbered(b)
    return not b.bad and b.top - settings.number_start == b.n - 1
end

function burst.ended(b)
    if not burst.numbered(b) then return false end
    local top_short = b.top_size ~= VRPO_MAX_DATA and 1 or 0
    if b.short ~= top_short then return false end -- a packet other than the last is short
    if settings.data_size > 0 then return b.size == settings.data_size end
    return top_short == 1
end

function burst.complete(b)
    return burst.ended(b) or b.short == 0 and settings.data_size == 0 and b.n >= b.need and burst.numbered(b)
end

-- A burst is over once it has ended; when the packet `number` restarts the numbering (the start
-- number again); or (size inferred) when it has the inferred size and `number` does not go on from
-- it: the sender's next packet begins another, even within the gap. `cur`: the sender's current
-- burst.
function burst.over(cur, number)
    local start, infer = settings.number_start, settings.data_size == 0
    local b = cur.b
    if b then
        return burst.ended(b) or number == start and b.seen[start] == true
            or infer and b.short == 0 and b.need > 0 and b.n >= b.need and number ~= b.top + 1 and burst.numbered(b)
    end
    return cur.number == start and (number == start or burst.alone_ended(cur.size)
        or infer and cur.size == VRPO_MAX_DATA and cur.need == 1 and number ~= start + 1)
end

-- Whether one packet numbered first, of data length `size`, ends a burst by itself.
function burst.alone_ended(size)
    local data_size = settings.data_size
    return data_size > 0 and size == data_size or data_size == 0 and size < VRPO_MAX_DATA
end

-- Whether one packet (packet number, data length, the burst's `need` if it was kept) is a
-- complete burst by itself.
function burst.alone(number, size, need)
    return number == settings.number_start and (burst.alone_ended(size)
        or settings.data_size == 0 and size == VRPO_MAX_DATA and need ~= nil and need <= 1)
end

-- The burst `cur` is over: a complete one of full packets raises the sender's `full`.
function burst.learn(snd, cur)
    local b = cur.b
    if b then
        if b.short == 0 and burst.complete(b) and b.n > snd.full then snd.full = b.n end
    elseif cur.size == VRPO_MAX_DATA and snd.full < 1 and burst.alone(cur.number, cur.size, cur.need) then
        snd.full = 1
    end
end

-- The data of a complete burst in number order (built once per burst length: O(n) per burst).
function burst.data(b)
    if b.data_n == b.n then return b.data end
    local n, start, by_number = b.n, settings.number_start, {}
    for i = 1, n do by_number[b[3 * i - 1] - start + 1] = b[3 * i] end
    local data = concat(by_number)
    b.data, b.data_n = data, n
    return data
end

-- (Functions in a table: the main chunk's locals are limited to 200.)
local sender_rec = {}

-- A sender's name as analyze gives it, "Input 10.0.0.10:5825 origin 0x0101" (IPv6 in brackets): its
-- statistics section, filtered or not.
function sender_rec.name(direction, addr, port, origin)
    local shown = addr:find(":", 1, true) and "[" .. addr .. "]" or addr
    return fmt("%s %s:%d origin 0x%04x", direction, shown, port, origin)
end

function sender_rec.new(name, port)
    local snd = { name = name, port = port, count = {}, duplicates = 0, late = 0, retransmissions = 0,
        states = {}, commands = 0, acked = 0, interrupted = 0, epoch = 0, open = {},
        cmds = { VRCI = {}, VRCO = {} }, -- kind -> command ID -> the sender's latest command with it
        restarts = {},  -- restart records, in order
        last = false,   -- time of its last legal packet
        pred = false, taken_over = false, -- new-port restarts: the sender it restarted, the one restarting it
        last_counter = false, -- (per-type scope) the counter of its last legal packet
        intervals = {}, -- type -> {last = time, frame, offset, n, min, max, sum}
        -- the current VRPO burst while it has one packet: no table of its own (most bursts)
        burst = { b = false, tlast = false, tstart = false, offset = false, frame = false, number = false,
            size = false, data = false, need = 0 },
        -- the periodic data size inferred: a packet of fewer than 488 bytes seen; the most packets
        -- of a complete burst of full packets
        short_seen = false, full = 0 }
    sender_list[#sender_list + 1] = snd
    return snd
end

-- A result as a table (a number is the interval, -1 for none).
local function as_table(res)
    if type(res) == "number" then return { serial = 0, interval = res >= 0 and res } end
    return res
end

-- A burst table once a second VRPO packet joins: packet i at [3i - 2] frame, [3i - 1] packet
-- number, [3i] data (or their length where they were not kept, see analyse()). The first
-- packet's stored result is rewritten to point to it (still on the first pass).
local function join_burst(cur, res, frame, number, data, size)
    local b = cur.b
    if not b then
        b = { cur.frame, cur.number, cur.data, n = 1, size = cur.size, top = settings.number_start - 1,
            top_size = 0, short = 0, bad = false, seen = {}, complete = nil, data = false, data_n = false,
            need = cur.need }
        cur.b = b
        local first = as_table(memo_get(results, cur.frame, cur.offset))
        if cur.number > b.top + 1 then first.burst_missing = b.top + 1 end
        burst.part(b, cur.number, cur.size)
        first.burst, first.burst_index = b, 1
        memo_set(results, cur.frame, cur.offset, first)
    end
    res = as_table(res)
    local n = b.n + 1
    b.n, b.size = n, b.size + size
    b[3 * n - 2], b[3 * n - 1], b[3 * n] = frame, number, data
    if number > b.top + 1 then res.burst_missing = b.top + 1 end
    burst.part(b, number, size)
    res.burst, res.burst_index = b, n
    return res
end

-- The highest serial of a sender's counter (per-type scope: of this type's, else of the counter
-- of its last legal packet, a duplicate included).
local function highest(snd, id)
    local c = counters[snd]
    if not c or not settings.per_type then return c and c.h end
    return (c[id] or snd.last_counter).h
end

-- Senders by (origin, port, direction) then source address: no string built per packet. A new
-- sender from a host (direction, origin, address) heard before on another port restarts the
-- sender of that host heard last among those silent for at least 250 ms and not restarted on a
-- new port before: returned as a record.
local function sender_of(r, pinfo, t, frame)
    local port = WS.src_port(pinfo)
    local direction = r.info.direction
    local k = (r.origin * 65536 + port) * 2 + (direction == "Input" and 1 or 0)
    local by_addr = senders[k]
    if not by_addr then
        by_addr = {}
        senders[k] = by_addr
    end
    local addr = tostring(WS.src(pinfo))
    local snd = by_addr[addr]
    if snd then return snd end
    snd = sender_rec.new(sender_rec.name(direction, addr, port, r.origin), port)
    by_addr[addr] = snd
    local host = fmt("%s %d %s", direction, r.origin, addr)
    local others = hosts[host]
    if not others then
        hosts[host] = { snd }
        return snd
    end
    local pred = false
    for _, other in ipairs(others) do
        -- (one restarted on a new port already lives on in its successor: restarted no more)
        if not other.taken_over and ms(t - other.last) >= RULES.new_port_silence_ms
            and (not pred or other.last > pred.last) then
            pred = other
        end
    end
    others[#others + 1] = snd
    if not pred then return snd end
    snd.pred, pred.taken_over = pred, snd
    local rec = { of = pred, frame = frame, t = t, from = highest(pred, r.type) or 0, to = r.serial,
        port_from = pred.port, port_to = port, decided = true, confirmed = true }
    snd.restarts[1] = rec
    return snd, rec
end

-- Returns the frame's result: a number for most packets (the interval, -1 for none: keeps the
-- retained heap small for the collector), else a table.
local function analyse(r, s, pinfo, frame, offset)
    local id = r.type
    local t = WS.abs_ts(pinfo) -- (the periodic streams': its own time)
    local now = capture.clock -- (senders', serials' and commands': rules.md, "the analysis clock")
    if t > now then
        now, capture.clock = t, t
        if capture.waiting then expire(now) end -- (before this packet is judged)
    end
    local snd, restart = sender_of(r, pinfo, now, frame)
    snd.count[id] = (snd.count[id] or 0) + 1
    snd.last, dirty = now, true
    note_record(frame, t)
    local serial = r.serial
    local c, fresh
    if settings.per_type then
        local by_type = counters[snd]
        if not by_type then
            by_type = {}
            counters[snd] = by_type
        end
        c = by_type[id]
        if not c then
            c, fresh = new_counter(snd, serial, now), true
            by_type[id] = c
            snd.states[#snd.states + 1] = c
        end
        snd.last_counter = c -- (a restart on a new port may need it: highest(); per-type scope only)
    else
        c = counters[snd]
        if not c then
            c, fresh = new_counter(snd, serial, now), true
            counters[snd] = c
            snd.states[1] = c
        end
    end
    local res = false -- (a table only where a number cannot say it)
    if not fresh then
        local missing = classify(c, serial, now)
        if missing == DUPLICATE then
            snd.duplicates = snd.duplicates + 1
            return DUP_RES
        elseif missing ~= 0 then
            res = { serial = missing }
            if missing > 0 then
                c.gaps[#c.gaps][4] = res -- (the gap classify() just opened)
            elseif missing == LATE then
                snd.late = snd.late + 1
            elseif missing == CANDIDATE then
                local rec = { of = snd, frame = frame, t = now, from = c.h, to = serial,
                    decided = false, confirmed = false, released = false }
                c.cand, res.cand = rec, rec
                local last = capture.waiting_last
                if last then last.next_waiting = rec else capture.waiting = rec end
                capture.waiting_last = rec
                restart_event(rec)
            end
        end
    end
    if restart then
        res = res or { serial = 0 }
        res.restart = restart
        restart_event(restart)
    end
    local iv = false
    if id == "VRPI" or id == "VRPO" then -- accepted packets of a periodic stream
        local stats = snd.intervals[id]
        if stats then
            iv = ms(t - stats.last)
        else
            stats = { n = 0, min = false, max = false, sum = 0, silent = false }
            snd.intervals[id] = stats
            local before = snd.pred and snd.pred.intervals[id] -- (a new-port restart: from its last packet)
            if before then iv = ms(t - before.last) end
        end
        if iv then
            if stats.n == 0 then stats.min, stats.max = iv, iv end
            if iv < stats.min then stats.min = iv end
            if iv > stats.max then stats.max = iv end
            stats.sum, stats.n = stats.sum + iv, stats.n + 1
        end
        stats.last, stats.frame, stats.offset = t, frame, offset
    end
    local v = r.values
    if v.command_id then
        res = res or { serial = 0 }
        res.interval = iv
        command_event(id, v.command_id, snd, now, frame, res)
        return res
    end
    if res then
        res.interval = iv
    elseif iv and iv < 0 then -- (a negative number says "no interval")
        res = { serial = 0, interval = iv }
    end
    if r.data_len then
        local number, size, cur = v.packet_number, r.data_len, snd.burst
        -- The data are kept only where a reassembly may need them: a short first-numbered packet
        -- completes a burst only alone, and then its own packet shows them (most VRPO).
        local data = size
        if size == VRPO_MAX_DATA or number ~= settings.number_start then
            local start = r.decoded_end - size
            data = sub(s, start + 1, start + size)
        end
        -- (a step back: a new one; so is the packet after a burst that is over)
        if cur.tlast and t >= cur.tlast and ms(t - cur.tlast) < settings.burst_gap and not burst.over(cur, number) then
            res = join_burst(cur, res or iv or -1, frame, number, data, size)
        else
            -- A new burst: its interval from the previous burst's first packet (equal to the
            -- packet's interval, as a number result says, after a burst of one packet).
            local bi = cur.tstart and ms(t - cur.tstart)
            local infer = settings.data_size == 0
            if infer and cur.tstart and (cur.b or cur.size == VRPO_MAX_DATA) then burst.learn(snd, cur) end
            cur.b, cur.offset, cur.frame, cur.number, cur.size, cur.data = false, offset, frame, number, size, data
            cur.tstart, cur.need = t, snd.short_seen and math.huge or snd.full
            if bi ~= iv then
                res = res or { serial = 0, interval = iv }
                res.binterval = bi
            end
            if infer and size == VRPO_MAX_DATA then -- (judged alone by what came before)
                res = res or { serial = 0, interval = iv }
                res.need = cur.need
            end
        end
        if size < VRPO_MAX_DATA then snd.short_seen = true end
        cur.tlast = t
    end
    return res or iv or -1
end

-- Once the whole capture has been seen (before the first visited dissection, and for the
-- statistics; again when a live capture has grown since): candidates still undecided are out of
-- order, the commands behind them run, and each periodic stream whose last packet lies more than
-- its watchdog before the capture's last record is marked silent until the end (unless a sender
-- on a new port took over).
local function finalize()
    dirty = false
    expire(false)
    flush()
    for _, res in ipairs(silent_marks) do res.silent = nil end
    silent_marks = {}
    local last_record = capture.last
    if not last_record then return end
    for _, snd in ipairs(sender_list) do
        for _, stats in pairs(snd.intervals) do stats.silent = false end
        if not snd.taken_over then
            for id, stats in pairs(snd.intervals) do
                local gap = ms(last_record - stats.last)
                if gap > (id == "VRPI" and settings.vrpi_watchdog or settings.vrpo_watchdog) then
                    local res = as_table(memo_get(results, stats.frame, stats.offset))
                    memo_set(results, stats.frame, stats.offset, res)
                    res.silent = gap
                    silent_marks[#silent_marks + 1] = res
                    stats.silent = gap
                end
            end
        end
    end
end

-- Machine-specific sub-dissectors, keyed by the "Machine" preference (see the README and
-- dissector/examples/crane.lua): they get the (reassembled) periodic data or the 16 bytes of
-- command data as their tvb; pinfo.private.vm110_type tells them the packet type.
-- A machine plugin that loads first creates the tables itself (see the example).
local function table_named(name, description)
    local ok, t = pcall(DissectorTable.get, name)
    if ok and t then return t end
    return DissectorTable.new(name, description, ftypes.STRING)
end
local machine_data = { -- (a table: the main chunk may have at most 200 locals)
    periodic = table_named("vm110.periodic_data", "VM-110 periodic data (machine-specific)"),
    command = table_named("vm110.command_data", "VM-110 command data (machine-specific)"),
}

function machine_data.dissect(table_, data_tvb, pinfo, tree)
    record = new_record() -- (the caller's record stays its own: see decode())
    table_:try(settings.machine, data_tvb, pinfo, tree)
end

-- What a packet carries alone: its command data, or its periodic data (when the caller knows them
-- to be a whole burst).
function machine_data.own(r, tvb, pinfo, tree)
    if r.values.command_data then
        pinfo.private.vm110_type = r.type
        local data = FIELDS.command_data
        machine_data.dissect(machine_data.command, range(tvb, data.off, data[2]):tvb(), pinfo, tree)
    elseif r.data_len > 0 then
        local data_tvb = range(tvb, PREFIX_LEN + VRPO_HEADER_SIZE, r.data_len):tvb()
        machine_data.dissect(machine_data.periodic, data_tvb, pinfo, tree)
    end
end

-- Expert summaries are constant (Wireshark's expert statistics group by them): the numbers are
-- in the fields they sit on. Every finding goes through finding(): its expert, and its name for
-- the Info column and vm110.analysis.flags, which show_findings() writes once the packet's
-- analysis is complete.
-- The packet being dissected: its findings' names in order (found[1 .. found.n]) and its
-- "[VM-110 analysis]" subtree (`at`; the protocol item when the tree is invisible).
local found = { n = 0, at = false }

local function finding(item, code, name)
    add_expert(item, E[code])
    name = name or FINDING[code]
    local n = found.n
    for i = 1, n do
        if found[i] == name then return end
    end
    found.n = n + 1
    found[n + 1] = name
end

-- The subtree that holds every analysis item of a packet, as TCP's "[SEQ/ACK analysis]".
local function analysis_tree(tvb, root, r)
    local at = root
    if want.visible then
        at = tree_add(root, range(tvb, 0, r.n), "VM-110 analysis")
        set_generated(at) -- (shown in brackets: "[VM-110 analysis]")
    end
    found.n, found.at = 0, at
    return at
end

-- The findings in front of the Info column ("[Serial Gap] [Watchdog] VRPI ...", as
-- "[TCP Retransmission]"), in the protocol item's label, and in vm110.analysis.flags.
local function show_findings(r, tvb, root, pinfo)
    local n = found.n
    if want.analysis_flags then
        generated(found.at or root, "analysis_flags", tvb, 0, r.n, concat(found, ", ", 1, n))
    end
    if want.columns or want.visible then
        local markers = "[" .. concat(found, "] [", 1, n) .. "] "
        if want.columns then pinfo.cols.info:prepend(markers) end
        if want.visible then root:set_text("VM-110 EG-Link, " .. markers .. r.info_text) end
    end
    found.n, found.at = 0, false
end

local function add_restart(rec, tvb, root)
    finding(generated(root, "restart", tvb, SERIAL_OFF, SERIAL_LEN, rec.from), "restart")
    if rec.port_from then generated(root, "restart_port_from", tvb, SERIAL_OFF, SERIAL_LEN, rec.port_from) end
end

local function add_serial_analysis(res, tvb, root)
    local missing = res.serial
    if missing > 0 then
        finding(generated(root, "serial_missing", tvb, SERIAL_OFF, SERIAL_LEN, missing), "serial_gap")
    elseif missing == DUPLICATE then
        finding(generated(root, "serial_duplicate", tvb, SERIAL_OFF, SERIAL_LEN, 1), "serial_duplicate")
    elseif missing == LATE or missing == CANDIDATE and res.cand.decided and not res.cand.confirmed then
        finding(generated(root, "serial_out_of_order", tvb, SERIAL_OFF, SERIAL_LEN, 1), "serial_out_of_order")
    elseif missing == CANDIDATE and res.cand.confirmed then
        add_restart(res.cand, tvb, root)
    end
    if res.restart then add_restart(res.restart, tvb, root) end
end

local function add_interval(iv, tvb, root, r)
    local item = generated(root, "interval", tvb, 0, ID_LEN, iv)
    if iv < 0 then
        finding(item, "time_backwards")
    elseif r.type == "VRPI" then
        if iv > settings.vrpi_watchdog then finding(item, "watchdog_vrpi") end
    elseif iv > settings.vrpo_watchdog then
        finding(item, "watchdog_vrpo")
    end
end

-- On a VRPO that begins a burst: the interval between burst starts (the VRPO period, which the
-- recommendation is about; the packets of a split burst go back to back).
local function add_burst_interval(bi, tvb, root)
    local item = generated(root, "burst_interval", tvb, 0, ID_LEN, bi)
    -- (a step back of the clock is time_backwards alone: one cause, one finding)
    if bi >= 0 and (bi < settings.vrpo_min or bi > settings.vrpo_max) then finding(item, "vrpo_interval") end
end

local function add_command_analysis(res, tvb, root, visited)
    local id = PREFIX_LEN -- generated fields point at the command ID
    local cmd = res.cmd
    if cmd then
        if res.number > 0 then
            local item = generated(root, "retransmission_of", tvb, id, 2, cmd.frame)
            if res.spurious then -- ("[VRCI Spurious Retransmission]", as TCP's)
                add_expert(item, E.retransmission)
                finding(item, "spurious_retransmission", cmd.type .. " Spurious Retransmission")
            else
                finding(item, "retransmission", cmd.type .. " Retransmission")
            end
            generated(root, "retransmission_number", tvb, id, 2, res.number)
            generated(root, "since_first", tvb, id, 2, res.since)
            local resend = generated(root, "resend_interval", tvb, id, 2, res.resend)
            if math.abs(res.resend - settings.resend) > settings.resend_tolerance then
                finding(resend, "resend_interval")
            end
        end
        if cmd.ack then
            local item = generated(root, "ack_in", tvb, id, 2, cmd.ack)
            if res.number == 0 and cmd.ack_ms > timeout_of(cmd) then finding(item, "ack_late") end
        elseif res.number == 0 then
            if cmd.interrupted then
                finding(generated(root, "interrupted_by", tvb, id, 2, cmd.interrupted), "command_interrupted")
            elseif visited then
                finding(root, "never_acked")
            end
        end
        return
    end
    local target = res.ack_of
    if not target then
        finding(root, "ack_without_command")
        return
    end
    generated(root, "ack_to", tvb, id, 2, target.frame)
    local item = generated(root, "ack_time", tvb, id, 2, res.ack_ms)
    if res.duplicate_ack then
        finding(item, "duplicate_ack")
        return
    end
    generated(root, "ack_time_last", tvb, id, 2, res.ack_last_ms)
    if res.ack_ms > timeout_of(target) then finding(item, "ack_late") end
end

local BURST_FRAMES_SHOWN = 64

local function add_burst(res, tvb, root, pinfo, tree, visited)
    local b = res.burst
    local n = b.n
    local bt = root
    if want.visible then
        bt = tree_add(root, range(tvb, NUMBER_OFF, NUMBER_LEN), fmt("VRPO burst: %d packet(s), %d bytes", n, b.size))
        set_generated(bt)
    end
    generated(bt, "burst_packets", tvb, NUMBER_OFF, NUMBER_LEN, n)
    generated(bt, "burst_size", tvb, NUMBER_OFF, NUMBER_LEN, b.size)
    if want.burst_frame then
        -- (VRPO packets closer than the burst gap that never end a burst would make this list long)
        for i = 1, n < BURST_FRAMES_SHOWN and n or BURST_FRAMES_SHOWN do
            generated(bt, "burst_frame", tvb, NUMBER_OFF, NUMBER_LEN, b[3 * i - 2])
        end
    end
    if res.burst_missing then
        finding(bt, "burst_missing")
    end
    if b[3 * n - 2] ~= pinfo.number then return end -- the data are shown with the burst's last packet
    local complete = b.complete
    if complete == nil then
        complete = burst.complete(b) -- (constant time: on the first pass every packet is the last so far)
        if visited then b.complete = complete end -- final once every frame has been seen
    end
    if not complete then
        if visited then
            finding(generated(bt, "burst_complete", tvb, NUMBER_OFF, NUMBER_LEN, false), "burst_incomplete")
        end
        return
    end
    generated(bt, "burst_complete", tvb, NUMBER_OFF, NUMBER_LEN, true)
    pinfo.cols.info:append(fmt(" [reassembled %d bytes]", b.size))
    local machine = settings.machine ~= ""
    if want.visible or want.reassembled or machine then -- (a new data source: only when shown or used)
        local data = burst.data(b)
        local data_tvb = ByteArray.new(data, true):tvb("Reassembled periodic data")
        if want.reassembled then tree_add(bt, F.reassembled, tvb_range(data_tvb, 0, #data)) end
        if machine then machine_data.dissect(machine_data.periodic, data_tvb, pinfo, tree) end
    end
end

-- A VRPO packet alone in its burst (so far, on the first pass): complete when it is numbered
-- first and its data end the burst.
local function add_single_burst(r, need, tvb, root, pinfo, tree, visited)
    local number, size, start = r.values.packet_number, r.data_len, settings.number_start
    if burst.alone(number, size, need) then
        generated(root, "burst_complete", tvb, NUMBER_OFF, NUMBER_LEN, true)
        if settings.machine ~= "" then machine_data.own(r, tvb, pinfo, tree) end
        return
    end
    if number > start then
        finding(root, "burst_missing")
    end
    if visited then
        finding(generated(root, "burst_complete", tvb, NUMBER_OFF, NUMBER_LEN, false), "burst_incomplete")
    end
end

local function add_silence(res, tvb, root)
    finding(generated(root, "silent_until_end", tvb, 0, ID_LEN, res.silent), "silent_until_end")
end

local function add_analysis(res, r, tvb, pinfo, tree, root)
    local visited = pinfo.visited
    add_serial_analysis(res, tvb, root)
    local iv = res.interval
    if iv then add_interval(iv, tvb, root, r) end
    if res.silent then add_silence(res, tvb, root) end
    if res.cmd or res.ack_of ~= nil then add_command_analysis(res, tvb, root, visited) end
    local duplicate = res.serial == DUPLICATE -- (a duplicate is no burst part)
    if res.burst and not duplicate then
        if res.burst_index == 1 then
            local bi = res.binterval
            if bi == nil then bi = iv end
            if bi then add_burst_interval(bi, tvb, root) end
        end
        add_burst(res, tvb, root, pinfo, tree, visited)
    elseif r.data_len and not duplicate then
        local bi = res.binterval
        if bi == nil then bi = iv end
        if bi then add_burst_interval(bi, tvb, root) end
        add_single_burst(r, res.need, tvb, root, pinfo, tree, visited)
    end
    if r.values.command_data and settings.machine ~= "" then machine_data.own(r, tvb, pinfo, tree) end
end

function vm110.init()
    crc_memo = new_memo()
    first_pass_view, second_pass_view = false, false
    reset_analysis()
    read_settings()
end

local function dissect(tvb, pinfo, tree)
    if not WS.number then WS.init(pinfo) end
    local visited = not settings.single_pass and WS.visited(pinfo)
    want = choose_view(tree, pinfo, visited)
    dissection = dissection + 1
    local number = WS.number(pinfo)
    local offset = WS.offset(tvb)
    local s = WS.raw(tvb)
    local res, known -- the frame's analysis and calculated CRC, from the first pass
    if visited then
        known = memo_get(crc_memo, number, offset) or nil
        if settings.analysis then
            if dirty then finalize() end
            res = memo_get(results, number, offset)
            if res and not known then known = true end -- (analysed: no problems, so the CRC matched)
        end
    end
    local r = decode(s, settings.variant, settings.big_endian, known)
    if r.problems ~= EMPTY then -- (only then: C calls)
        -- (a quote is cut where its header's size says more: decode() tells)
        local cut = tvb:reported_len() > r.n and "snaplen" or WS.fragmented(pinfo) and "fragment"
            or WS.in_error_pkt(pinfo) and "quote"
        if cut then r = decode(s, settings.variant, settings.big_endian, known, cut) end
    end
    local legal = r.problems == EMPTY -- (own() replaces EMPTY at the first problem)
    if r.crc_calc and not known and not settings.single_pass and not (settings.analysis and legal) then
        memo_set(crc_memo, number, offset, r.crc_calc) -- (an analysed packet's is its stored CRC)
    end
    if want.visible or want.columns then r.info_text = summary(r) end -- (the root item's label too)
    if want.columns then
        local cols = pinfo.cols
        cols.protocol = "VM110"
        cols.info = r.info_text
    end
    local root = add_tree(r, tvb, tree)
    if settings.analysing then
        if not visited then -- (tshark -2 -R gives a frame the read filter drops the number of the next one it keeps)
            res = false
            -- (a datagram quoted in an ICMP error was not received: analyze reads no ICMP either)
            if legal and not WS.in_error_pkt(pinfo) then
                res = analyse(r, s, pinfo, number, offset)
            else -- (not analysed, but the capture's last record so far)
                note_record(number, WS.abs_ts(pinfo))
            end
            memo_set(results, number, offset, res)
        end
        if type(res) == "number" then
            if res >= 0 or r.data_len then
                local at = analysis_tree(tvb, root, r)
                if res >= 0 then
                    add_interval(res, tvb, at, r)
                    if r.data_len then add_burst_interval(res, tvb, at) end -- (a number: equal)
                end
                if r.data_len then add_single_burst(r, nil, tvb, at, pinfo, tree, visited) end
            end
        elseif res then
            add_analysis(res, r, tvb, pinfo, tree, analysis_tree(tvb, root, r))
        end
        if found.n > 0 then show_findings(r, tvb, root, pinfo) end
        -- (for the statistics with a filter: an analysed packet's record)
        found.r, found.number, found.offset = res and r, number, offset
    elseif legal and settings.machine ~= "" then -- (no reassembly: what a packet carries alone)
        local v = r.values
        if v.command_data or r.data_len and burst.alone(v.packet_number, r.data_len) then
            machine_data.own(r, tvb, pinfo, tree)
        end
    end
    return r.n
end
vm110.dissector = dissect
vm110_handle = Dissector.get("vm110")

-- On another port: a packet ID and a size that agrees with the length. On the EG-Link ports, any
-- datagram: there the heuristic runs only when tried first (udp.try_heuristic_first, as analyze's
-- tshark engine runs), and takes the datagram before Wireshark gives it to a lower port's
-- dissector (a damaged source port of 5683: CoAP's), as the EG-Link ports' own reader does.
local function heuristic(tvb, pinfo, tree)
    if not settings.heuristic then return false end
    local port, src, dst = settings.port, pinfo.src_port, pinfo.dst_port
    local ours = src == port or dst == port or src == port + OUTPUT_PORT_OFFSET or dst == port + OUTPUT_PORT_OFFSET
    if not ours then
        -- The length sent, not the length captured (a datagram the snaplen cut is truncated here
        -- too); a first IP fragment or an ICMP error's quote holds only the beginning of one.
        if tvb:len() < PREFIX_LEN or not TYPES[tvb:raw(0, ID_LEN)] then return false end
        local n, sent = tvb:reported_len(), OVERHEAD + tvb(10, 2):le_uint()
        if sent > OVERHEAD + MAX_PAYLOAD or sent ~= n
            and not (n < sent and (pinfo.fragmented or pinfo.in_error_pkt)) then -- (rare: no WS)
            return false
        end
    end
    dissect(tvb, pinfo, tree) -- not vm110.dissector: that is a handle, and would add the layer twice
    return true
end

local udp_port = DissectorTable.get("udp.port")
local function register_ports() -- (settings.port: the input port registered)
    local port, old = floor(settings.input_port), settings.port -- (an integer on Lua 5.4 too)
    if port == old then return end
    if old then
        udp_port:remove(old, vm110)
        udp_port:remove(old + OUTPUT_PORT_OFFSET, vm110)
    end
    udp_port:add(port, vm110)
    udp_port:add(port + OUTPUT_PORT_OFFSET, vm110)
    settings.port = port
end

function vm110.prefs_changed()
    crc_memo = new_memo()
    first_pass_view, second_pass_view = false, false
    cmdline_view = false
    reset_analysis()
    read_settings()
    register_ports()
end

-- The capture's last record, of any kind (a stream silent until the end is measured to it): the
-- dissector sees its own frames. The others: in the GUI and tshark -2 (whose first pass runs no
-- taps) a postdissector, a Lua call with its userdata for every frame (on a pure EG-Link capture
-- the largest single cost of this file's). A single-pass tshark prints each frame before the next
-- is read, so that nothing it prints can depend on the end: there only the statistics (-z
-- vm110,stat) read it, and they ask for a tap filtered to the other frames (a filter run on every
-- frame, which costs about as much as the postdissector).
local watch_other_frames -- (its state in a block: the main chunk may have at most 200 locals)
do
    -- (pinfo's getters as the C functions, and the time read only for a new last record: on a
    -- visited frame, which never is one, a single C call)
    local function other_frame(_, pinfo)
        if not settings.analysis then return end
        if not WS.number then WS.init(pinfo) end
        local n = WS.number(pinfo)
        if n > capture.number then note_record(n, WS.abs_ts(pinfo)) end
    end
    local tap = false
    function watch_other_frames()
        if not settings.single_pass or tap then return end
        tap = Listener.new("frame", "not vm110")
        function tap.packet(pinfo) other_frame(nil, pinfo) end
    end
    if not settings.single_pass then
        local capture_end = Proto("vm110_end", "VM-110 EG-Link stream analysis: the capture's last record")
        capture_end.dissector = other_frame
        register_postdissector(capture_end)
    end
end

read_settings()
register_ports()
udp_port:add_for_decode_as(vm110)
vm110:register_heuristic("udp", heuristic)

---------------------------------------------------------------------------------------------
-- Statistics: `tshark -z vm110,stat` and Statistics → VM-110 EG-Link Stream Statistics (GUI),
-- from the state the analysis built on the first pass.
---------------------------------------------------------------------------------------------
local STAT_TYPES = { "VRPI", "VRPO", "VRCI", "VRCO", "VRAI", "VRAO" }

local function stats_text()
    local out = { "VM-110 EG-Link stream statistics" }
    if not settings.analysis then out[2] = "(stream analysis is off: preference vm110.analysis)" end
    if dirty then finalize() end
    for _, snd in ipairs(sender_list) do
        local lost, wraps = 0, 0
        for _, st in ipairs(snd.states) do lost, wraps = lost + st.lost, wraps + st.wraps end
        local types = {}
        for _, id in ipairs(STAT_TYPES) do
            if snd.count[id] then types[#types + 1] = fmt("%s %d", id, snd.count[id]) end
        end
        out[#out + 1] = "Sender " .. snd.name
        out[#out + 1] = "  Packets: " .. concat(types, ", ")
        out[#out + 1] = fmt("  Serial: lost %d, duplicates %d, out of order %d, wraps %d, restarts %d", lost,
            snd.duplicates, snd.late, wraps, #snd.restarts)
        for _, rec in ipairs(snd.restarts) do
            local port = rec.port_from and fmt(", port %d -> %d", rec.port_from, rec.port_to) or ""
            out[#out + 1] = fmt("  Restart in frame %d: serial %d -> %d%s", rec.frame, rec.from, rec.to, port)
        end
        out[#out + 1] = fmt("  Commands: %d, acked %d, unacknowledged %d, interrupted %d, retransmissions %d",
            snd.commands, snd.acked, snd.commands - snd.acked - snd.interrupted, snd.interrupted, snd.retransmissions)
        for _, id in ipairs({ "VRPI", "VRPO" }) do
            local stats = snd.intervals[id]
            if stats and stats.n > 0 then
                out[#out + 1] = fmt("  %s interval (ms): min %.3f, avg %.3f, max %.3f (%d intervals)", id,
                    stats.min, stats.sum / stats.n, stats.max, stats.n)
            end
            if stats and stats.silent then
                out[#out + 1] = fmt("  %s silent until the end: %.3f ms after frame %d", id, stats.silent, stats.frame)
            end
        end
    end
    return concat(out, "\n") .. "\n"
end

-- With a display filter (`-z vm110,stat,FILTER`, or the GUI's display filter): the same figures,
-- of the packets the filter matches. A tap with the filter notes each matching analysed packet
-- (its sender, type, frame and offset: dissect() leaves them in `found`); the figures are read
-- from the packets' final analysis once every frame has been seen, so they are complete on a
-- single pass too (as far as the filter itself can match there). Per sender: packets by type;
-- lost (serials missing before the matching packets and never received later), duplicates, out
-- of order and restarts at them; commands first sent in them, with those acknowledged, interrupted and unacknowledged;
-- retransmissions among them; their intervals; a silence until the end after one of them.
local filtered_stats = {}

function filtered_stats.tap_filter(filter)
    return "vm110 && (" .. filter .. ")"
end

function filtered_stats.new(filter)
    local acc = { filter = filter, list = {} }
    local tap = Listener.new("frame", filtered_stats.tap_filter(filter))
    function tap.packet(pinfo)
        local r = found.r
        if not r or found.number ~= pinfo.number then return end
        local list = acc.list
        list[#list + 1] = { sender_rec.name(r.info.direction, tostring(pinfo.src), pinfo.src_port, r.origin), r.type,
            found.number, found.offset }
    end
    function tap.reset() acc.list = {} end
    acc.tap = tap
    return acc
end

function filtered_stats.text(acc)
    local out = { "VM-110 EG-Link stream statistics", "Display filter: " .. acc.filter }
    if not settings.analysis then out[3] = "(stream analysis is off: preference vm110.analysis)" end
    if dirty then finalize() end
    local by_name, order = {}, {}
    for _, p in ipairs(acc.list) do
        local name, id = p[1], p[2]
        local s = by_name[name]
        if not s then
            s = { count = {}, lost = 0, duplicates = 0, late = 0, restarts = {}, commands = 0, acked = 0,
                interrupted = 0, retransmissions = 0, intervals = {}, silent = {} }
            by_name[name] = s
            order[#order + 1] = name
        end
        s.count[id] = (s.count[id] or 0) + 1
        local res = memo_get(results, p[3], p[4])
        local iv = type(res) == "number" and res >= 0 and res -- (a number result: -1 for no interval)
        if type(res) == "table" then
            iv = res.interval
            local missing = res.serial
            if missing > 0 then
                s.lost = s.lost + missing - (res.filled or 0) -- (as the whole capture's: net of late packets)
            elseif missing == DUPLICATE then
                s.duplicates = s.duplicates + 1
            elseif missing == LATE or missing == CANDIDATE and res.cand.decided and not res.cand.confirmed then
                s.late = s.late + 1
            elseif missing == CANDIDATE and res.cand.confirmed then
                s.restarts[#s.restarts + 1] = res.cand
            end
            if res.restart then s.restarts[#s.restarts + 1] = res.restart end
            local cmd = res.cmd
            if cmd and res.number == 0 then
                s.commands = s.commands + 1
                if cmd.ack then
                    s.acked = s.acked + 1
                elseif cmd.interrupted then
                    s.interrupted = s.interrupted + 1
                end
            elseif cmd then
                s.retransmissions = s.retransmissions + 1
            end
            if res.silent then s.silent[id] = { res.silent, p[3] } end
        end
        if iv and (id == "VRPI" or id == "VRPO") then -- (a negative one, time going back, counts: as unfiltered)
            local st = s.intervals[id]
            if not st then
                st = { n = 0, sum = 0, min = iv, max = iv }
                s.intervals[id] = st
            end
            st.n, st.sum = st.n + 1, st.sum + iv
            if iv < st.min then st.min = iv end
            if iv > st.max then st.max = iv end
        end
    end
    for _, name in ipairs(order) do
        local s = by_name[name]
        local types = {}
        for _, id in ipairs(STAT_TYPES) do
            if s.count[id] then types[#types + 1] = fmt("%s %d", id, s.count[id]) end
        end
        out[#out + 1] = "Sender " .. name
        out[#out + 1] = "  Packets: " .. concat(types, ", ")
        out[#out + 1] = fmt("  Serial: lost %d, duplicates %d, out of order %d, restarts %d", s.lost, s.duplicates,
            s.late, #s.restarts)
        for _, rec in ipairs(s.restarts) do
            local port = rec.port_from and fmt(", port %d -> %d", rec.port_from, rec.port_to) or ""
            out[#out + 1] = fmt("  Restart in frame %d: serial %d -> %d%s", rec.frame, rec.from, rec.to, port)
        end
        out[#out + 1] = fmt("  Commands: %d, acked %d, unacknowledged %d, interrupted %d, retransmissions %d",
            s.commands, s.acked, s.commands - s.acked - s.interrupted, s.interrupted, s.retransmissions)
        for _, id in ipairs({ "VRPI", "VRPO" }) do
            local st = s.intervals[id]
            if st then
                out[#out + 1] = fmt("  %s interval (ms): min %.3f, avg %.3f, max %.3f (%d intervals)", id,
                    st.min, st.sum / st.n, st.max, st.n)
            end
            local silent = s.silent[id]
            if silent then
                out[#out + 1] = fmt("  %s silent until the end: %.3f ms after frame %d", id, silent[1], silent[2])
            end
        end
    end
    if #order == 0 then out[#out + 1] = "(no EG-Link packet matches the filter)" end
    return concat(out, "\n") .. "\n"
end

-- `-z vm110,stat` (the whole capture) or `-z vm110,stat,FILTER` (the packets FILTER matches), as
-- Wireshark's own statistics take a filter.
if register_stat_cmd_arg then
    register_stat_cmd_arg("vm110,stat", function(arg)
        watch_other_frames()
        local filter = type(arg) == "string" and arg:match("^vm110,stat,(.+)$") or nil
        if filter and filter:match("%S") then
            local ok, acc = pcall(filtered_stats.new, filter)
            if not ok then
                io.stderr:write(fmt("vm110,stat: the display filter %q does not compile: %s\n", filter, tostring(acc)))
                error(acc)
            end
            function acc.tap.draw() io.write(filtered_stats.text(acc)) end
            return
        end
        local tap = Listener.new("frame", "vm110")
        function tap.draw() io.write(stats_text()) end
    end)
end
-- GUI only: these functions exist when Wireshark runs with a GUI. The Qt GUI shows a Lua menu of
-- MENU_STAT_UNSORTED in Statistics (not one of MENU_STAT_GENERIC), and a "/" in its name as is.
-- The window takes the display filter applied at the time (like Wireshark's statistics with
-- "Limit to display filter"); its "Display filter..." button asks for another one.
local MENU_NAME = "VM-110 EG-Link Stream Statistics"
local function stats_window(filter)
    local title = MENU_NAME
    if filter and filter:match("%S") then title = MENU_NAME .. " (" .. filter .. ")" end
    local win = TextWindow.new(title)
    if win.add_button and new_dialog then
        win:add_button("Display filter...", function()
            new_dialog(MENU_NAME, function(text) stats_window(text) end, "Display filter (empty: every packet)")
        end)
    end
    if not (filter and filter:match("%S")) then
        win:set(stats_text())
        return
    end
    local ok, acc = pcall(filtered_stats.new, filter)
    if not ok then
        win:set("Display filter: " .. filter .. "\n" .. tostring(acc) .. "\n")
        return
    end
    function acc.tap.draw() win:set(filtered_stats.text(acc)) end
    if win.set_atclose then win:set_atclose(function() acc.tap:remove() end) end
    if retap_packets then retap_packets() end
end
if gui_enabled and gui_enabled() and register_menu then
    register_menu(MENU_NAME, function()
        local ok, filter = pcall(get_filter) -- (raises when there is no main window)
        stats_window(ok and filter or "")
    end, MENU_STAT_UNSORTED)
end
