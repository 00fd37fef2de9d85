-- luacheck configuration for the dissector (dissector/vm110.lua) and its examples.
-- The code runs on Lua 5.2 (Wireshark 4.0) and Lua 5.4 (Wireshark 4.4, 4.6): "min" allows only
-- the globals every Lua version has (no bit32, no unpack, no setfenv), plus table.unpack, which
-- both 5.2 and 5.4 have. The Wireshark Lua API is read-only globals.
stds.lua52_54 = {
    read_globals = { table = { fields = { "unpack" } } },
}
stds.wireshark = {
    read_globals = {
        "Proto", "ProtoField", "ProtoExpert", "Pref", "Field", "DissectorTable", "Dissector", "Listener",
        "TreeItem", "Tvb", "TvbRange", "ByteArray", "TextWindow", "base", "ftypes", "expert", "frametype",
        "set_plugin_info", "register_postdissector", "register_stat_cmd_arg", "register_menu", "new_dialog",
        "retap_packets", "gui_enabled", "get_filter", "reset_preference", "MENU_STAT_UNSORTED", "MENU_TOOLS_UNSORTED",
        "bit", -- LuaBitOp, which Wireshark ships for Lua 5.2 (the CRC uses it there only)
    },
}
stds.wireshark.read_globals[#stds.wireshark.read_globals + 1] = "report_failure"
std = "min+lua52_54+wireshark"
max_line_length = 120
-- Callbacks take Wireshark's arguments in order; an unused one is named with a leading underscore.
ignore = { "212/_.*" }
