-- Example machine-specific sub-dissector for dissector/vm110.lua: a (fictitious) crane.
--
-- TS-0006 leaves the meaning of VRPO periodic data and of VRCI/VRCO command data to each
-- machine. vm110.lua hands them to two dissector tables keyed by its "Machine" preference:
--   vm110.periodic_data  the periodic data of a VRPO burst (reassembled when it was split)
--   vm110.command_data   the 16 command data bytes of a VRCI or VRCO
-- A machine plugin adds itself to both under a name of its choice and the user selects it
-- with Edit → Preferences → Protocols → VM110 → Machine (or -o vm110.machine:crane).
--
-- Not loaded by vm110.lua. Use it with:
--   tshark -X lua_script:vm110.lua -X lua_script:examples/crane.lua -o vm110.machine:crane -r FILE
-- or copy it next to vm110.lua in the personal Lua plugin folder (either may load first: both
-- get the tables with table_named() below). A sample capture: captures/crane.pcapng (made by
-- captures/crane.py; captures/README.md describes it).
--
-- Crane periodic data (little-endian):
--   0  u16 hoist height (cm)      2  u16 load (kg)      4  u8 alarm bits      5  u8 speed limit (%)
--   6  u16 number of event log entries N, then N entries of 8 bytes: u32 time (s), u16 code, u16 value
-- (100 log entries make 808 bytes: more than one VRPO packet carries, so the data arrive split.)
-- Crane command data: u8 opcode, then its argument; the rest is zero.
--   VRCI (operator → machine): 0x01 set speed limit (u8 %), 0x02 reset alarms (u8 alarm mask),
--                              0x03 horn (u8 0 off / 1 on)
--   VRCO (machine → operator): 0x81 show alarm text (up to 15 bytes of ASCII)

-- The table, created here when this file loads before vm110.lua (vm110.lua does the same).
local function table_named(name, description)
    local ok, t = pcall(DissectorTable.get, name)
    if ok and t then return t end
    return DissectorTable.new(name, description, ftypes.STRING)
end
local periodic_table = table_named("vm110.periodic_data", "VM-110 periodic data (machine-specific)")
local command_table = table_named("vm110.command_data", "VM-110 command data (machine-specific)")

local crane = Proto("crane", "Crane (VM-110 machine data example)")
local ALARMS = { { 0x01, "Overload" }, { 0x02, "High wind" }, { 0x04, "Slack rope" }, { 0x08, "Limit switch" } }
local OPCODES = { [0x01] = "Set speed limit", [0x02] = "Reset alarms", [0x03] = "Horn", [0x81] = "Show alarm text" }

local f = {
    hoist_height = ProtoField.uint16("crane.hoist_height", "Hoist height (cm)", base.DEC),
    load = ProtoField.uint16("crane.load", "Load (kg)", base.DEC),
    alarms = ProtoField.uint8("crane.alarms", "Alarms", base.HEX),
    speed_limit = ProtoField.uint8("crane.speed_limit", "Speed limit (%)", base.DEC),
    log_count = ProtoField.uint16("crane.log_count", "Event log entries", base.DEC),
    log_time = ProtoField.uint32("crane.log.time", "Time (s)", base.DEC),
    log_code = ProtoField.uint16("crane.log.code", "Event code", base.HEX),
    log_value = ProtoField.uint16("crane.log.value", "Value", base.DEC),
    opcode = ProtoField.uint8("crane.opcode", "Command", base.HEX, OPCODES),
    new_speed_limit = ProtoField.uint8("crane.set_speed_limit", "New speed limit (%)", base.DEC),
    reset_mask = ProtoField.uint8("crane.reset_alarms", "Alarms to reset", base.HEX),
    horn = ProtoField.bool("crane.horn", "Horn on"),
    alarm_text = ProtoField.string("crane.alarm_text", "Alarm text"),
}
for _, a in ipairs(ALARMS) do
    local key = "alarm_" .. a[2]:lower():gsub(" ", "_")
    f[key] = ProtoField.bool("crane." .. key, a[2], 8, nil, a[1])
    a.field = f[key]
end
local list = {}
for _, field in pairs(f) do list[#list + 1] = field end
crane.fields = list

local bad_length = ProtoExpert.new("crane.bad_length", "Crane data shorter than its layout", expert.group.MALFORMED,
    expert.severity.ERROR)
crane.experts = { bad_length }

function crane.dissector(tvb, _pinfo, tree)
    local root = tree:add(crane, tvb())
    if tvb:len() < 8 then
        root:add_proto_expert_info(bad_length)
        return
    end
    root:add_le(f.hoist_height, tvb(0, 2))
    root:add_le(f.load, tvb(2, 2))
    local alarms = root:add(f.alarms, tvb(4, 1))
    for _, a in ipairs(ALARMS) do alarms:add(a.field, tvb(4, 1)) end
    root:add(f.speed_limit, tvb(5, 1))
    local count = tvb(6, 2):le_uint()
    root:add_le(f.log_count, tvb(6, 2))
    if tvb:len() < 8 + 8 * count then
        root:add_proto_expert_info(bad_length, string.format("%d log entries need %d bytes", count, 8 + 8 * count))
        return
    end
    for i = 0, count - 1 do
        local off = 8 + 8 * i
        local entry = root:add(tvb(off, 8), string.format("Event %d", i + 1))
        entry:add_le(f.log_time, tvb(off, 4))
        entry:add_le(f.log_code, tvb(off + 4, 2))
        entry:add_le(f.log_value, tvb(off + 6, 2))
    end
end

-- Command data of VRCI and VRCO: vm110.lua puts the packet type in pinfo.private.vm110_type.
local crane_commands = Proto("crane_cmd", "Crane command (VM-110 machine data example)")
function crane_commands.dissector(tvb, pinfo, tree)
    local root = tree:add(crane, tvb(), "Crane command")
    local opcode = tvb(0, 1):uint()
    root:add(f.opcode, tvb(0, 1))
    local kind = pinfo.private.vm110_type
    if kind == "VRCI" and opcode == 0x01 then
        root:add(f.new_speed_limit, tvb(1, 1))
        pinfo.cols.info:append(string.format(" (crane: speed limit %d%%)", tvb(1, 1):uint()))
    elseif kind == "VRCI" and opcode == 0x02 then
        root:add(f.reset_mask, tvb(1, 1))
    elseif kind == "VRCI" and opcode == 0x03 then
        root:add(f.horn, tvb(1, 1))
    elseif kind == "VRCO" and opcode == 0x81 then
        root:add(f.alarm_text, tvb(1, 15), tvb(1, 15):stringz())
    end
end

periodic_table:add("crane", crane)
command_table:add("crane", crane_commands)
