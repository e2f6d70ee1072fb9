"""What a shared library says about itself: format, architecture, exported symbols, dependencies.

A small reader of the headers of the three formats the compiled kernel ships in (64-bit little-endian
only, which is all we build): ELF (the dynamic section, .dynsym and the GNU symbol-version needs), PE32+
(COFF header, export, import and delay-import directories) and Mach-O (load commands, the export trie
dyld reads, the symbol table, the minimum OS version and the code signature's page hashes). Used by
tests/core/test_native_binaries.py to check the Windows and macOS libraries, which cannot run here, and
by tools/build_native.py to print what it built. No dependencies beyond the standard library.
"""

from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class BinaryInfo:
    """What `read` found. `needs` lists the libraries the loader must find, in file order."""

    format: str  # "ELF", "PE32+", "Mach-O"
    arch: str  # "x86_64", "arm64"
    kind: str  # "shared library" for what we build; anything else is wrong
    exports: set[str] = field(default_factory=set)
    needs: list[str] = field(default_factory=list)
    imports: set[str] = field(default_factory=set)  # undefined symbols (ELF, Mach-O) / imported names (PE)
    #: ELF: symbol versions needed per library ({"libm.so.6": {"GLIBC_2.2.5"}}).
    versions: dict[str, set[str]] = field(default_factory=dict)
    #: Anything else worth checking: ELF soname/runpath, PE unnamed exports, Mach-O minimum OS,
    #: install name, code signature.
    extra: dict[str, object] = field(default_factory=dict)


class FormatError(ValueError):
    pass


def read(path: str | Path) -> BinaryInfo:
    data = Path(path).read_bytes()
    if data[:4] == b"\x7fELF":
        return _elf(data)
    if data[:2] == b"MZ":
        return _pe(data)
    if data[:4] == struct.pack("<I", 0xFEEDFACF):
        return _macho(data)
    raise FormatError(f"{path}: not a 64-bit little-endian ELF, PE or Mach-O file (starts {data[:4]!r})")


def _cstr(data: bytes, offset: int) -> str:
    end = data.index(b"\0", offset)
    return data[offset:end].decode("utf-8", "replace")


# ------------------------------------------------------------------------------------------------- ELF

_ELF_MACHINES = {62: "x86_64", 183: "arm64"}
_SHT_DYNAMIC, _SHT_DYNSYM, _SHT_VERNEED = 6, 11, 0x6FFFFFFE
_DT_NEEDED, _DT_SONAME, _DT_RPATH, _DT_RUNPATH, _DT_TEXTREL = 1, 14, 15, 29, 22


def _elf(data: bytes) -> BinaryInfo:
    if data[4] != 2 or data[5] != 1:
        raise FormatError("ELF file is not 64-bit little-endian")
    (e_type, e_machine, _ver, _entry, _phoff, e_shoff, _flags, _ehsize, _phentsize, _phnum,
     e_shentsize, e_shnum, _shstrndx) = struct.unpack_from("<HHIQQQIHHHHHH", data, 16)
    kind = {3: "shared library", 2: "executable", 1: "relocatable"}.get(e_type, f"type {e_type}")
    info = BinaryInfo("ELF", _ELF_MACHINES.get(e_machine, f"machine {e_machine}"), kind)
    sections = [struct.unpack_from("<IIQQQQIIQQ", data, e_shoff + i * e_shentsize) for i in range(e_shnum)]

    def strtab(index: int, offset: int) -> str:
        return _cstr(data, sections[index][4] + offset)

    for _name, sh_type, _f, _a, off, size, link, _info, _al, entsize in sections:
        if sh_type == _SHT_DYNAMIC:
            for pos in range(off, off + size, entsize or 16):
                tag, value = struct.unpack_from("<qQ", data, pos)
                if tag == 0:
                    break
                if tag == _DT_NEEDED:
                    info.needs.append(strtab(link, value))
                elif tag == _DT_SONAME:
                    info.extra["soname"] = strtab(link, value)
                elif tag in (_DT_RPATH, _DT_RUNPATH):
                    info.extra["runpath"] = strtab(link, value)
                elif tag == _DT_TEXTREL:
                    info.extra["textrel"] = True
        elif sh_type == _SHT_DYNSYM:
            for pos in range(off + (entsize or 24), off + size, entsize or 24):  # entry 0 is null
                st_name, st_info, st_other, st_shndx, _value, _size = struct.unpack_from("<IBBHQQ", data, pos)
                name = strtab(link, st_name)
                bind, vis = st_info >> 4, st_other & 3
                if st_shndx == 0:
                    if name:
                        info.imports.add(name)
                elif bind in (1, 2, 10) and vis in (0, 3) and name:  # GLOBAL/WEAK/UNIQUE, DEFAULT/PROTECTED
                    info.exports.add(name)
        elif sh_type == _SHT_VERNEED:
            pos = off
            while True:
                _vn_version, vn_cnt, vn_file, vn_aux, vn_next = struct.unpack_from("<HHIII", data, pos)
                names = info.versions.setdefault(strtab(link, vn_file), set())
                aux = pos + vn_aux
                for _ in range(vn_cnt):
                    _hash, _flags, _other, vna_name, vna_next = struct.unpack_from("<IHHII", data, aux)
                    names.add(strtab(link, vna_name))
                    aux += vna_next
                if not vn_next:
                    break
                pos += vn_next
    return info


# -------------------------------------------------------------------------------------------------- PE

_PE_MACHINES = {0x8664: "x86_64", 0xAA64: "arm64", 0x14C: "x86"}


def _pe(data: bytes) -> BinaryInfo:
    (pe_offset,) = struct.unpack_from("<I", data, 0x3C)
    if data[pe_offset:pe_offset + 4] != b"PE\0\0":
        raise FormatError("MZ file without a PE header")
    machine, nsections, _time, _symptr, _nsyms, opt_size, characteristics = struct.unpack_from(
        "<HHIIIHH", data, pe_offset + 4)
    opt = pe_offset + 24
    (magic,) = struct.unpack_from("<H", data, opt)
    if magic != 0x20B:
        raise FormatError(f"PE optional header magic {magic:#x}, not PE32+")
    kind = "shared library" if characteristics & 0x2000 else "executable"
    info = BinaryInfo("PE32+", _PE_MACHINES.get(machine, f"machine {machine:#x}"), kind)
    (ndirs,) = struct.unpack_from("<I", data, opt + 108)
    dirs = [struct.unpack_from("<II", data, opt + 112 + 8 * i) for i in range(ndirs)]
    sections = [struct.unpack_from("<8sIIII", data, opt + opt_size + 40 * i) for i in range(nsections)]

    def offset(rva: int) -> int:
        for _name, vsize, vaddr, rawsize, rawptr in sections:
            if vaddr <= rva < vaddr + max(vsize, rawsize):
                return rva - vaddr + rawptr
        raise FormatError(f"RVA {rva:#x} is in no section")

    def directory(index: int) -> tuple[int, int]:
        return dirs[index] if index < len(dirs) else (0, 0)

    rva, _size = directory(0)
    if rva:
        fields = struct.unpack_from("<IIHHIIIIIII", data, offset(rva))
        nfunctions, nnames, names_rva = fields[6], fields[7], fields[9]
        for i in range(nnames):
            (name_rva,) = struct.unpack_from("<I", data, offset(names_rva) + 4 * i)
            info.exports.add(_cstr(data, offset(name_rva)))
        info.extra["unnamed_exports"] = nfunctions - nnames
    rva, _size = directory(1)
    if rva:
        pos = offset(rva)
        while True:
            lookup, _t, _fwd, name_rva, thunk = struct.unpack_from("<IIIII", data, pos)
            if not (lookup or name_rva or thunk):
                break
            info.needs.append(_cstr(data, offset(name_rva)))
            info.imports |= _pe_thunk_names(data, offset, lookup or thunk)
            pos += 20
    rva, _size = directory(13)
    if rva:
        pos = offset(rva)
        while True:
            _attrs, name_rva, *_rest = struct.unpack_from("<IIIIIIII", data, pos)
            if not name_rva:
                break
            info.needs.append(_cstr(data, offset(name_rva)))
            info.extra["delay_loaded"] = True
            pos += 32
    return info


def _pe_thunk_names(data: bytes, offset, rva: int) -> set[str]:
    names = set()
    pos = offset(rva)
    while True:
        (entry,) = struct.unpack_from("<Q", data, pos)
        if not entry:
            return names
        if not entry >> 63:  # by name (hint, name); else by ordinal
            names.add(_cstr(data, offset(entry & 0x7FFFFFFF) + 2))
        pos += 8


# ---------------------------------------------------------------------------------------------- Mach-O

_MACHO_CPUS = {0x01000007: "x86_64", 0x0100000C: "arm64"}
_LC_DYLIBS = {0xC: "load", 0x80000018: "weak", 0x8000001F: "reexport", 0x20: "lazy", 0x80000023: "upward"}
_LC_SYMTAB, _LC_ID_DYLIB, _LC_DYLD_INFO, _LC_DYLD_INFO_ONLY = 0x2, 0xD, 0x22, 0x80000022
_LC_DYLD_EXPORTS_TRIE, _LC_BUILD_VERSION, _LC_VERSION_MIN_MACOSX = 0x80000033, 0x32, 0x24
_LC_CODE_SIGNATURE, _LC_RPATH = 0x1D, 0x8000001C


def _version(packed: int) -> str:
    return f"{packed >> 16}.{(packed >> 8) & 0xFF}.{packed & 0xFF}"


def _macho(data: bytes) -> BinaryInfo:
    _magic, cputype, _sub, filetype, ncmds, _sizeofcmds, _flags, _res = struct.unpack_from("<IiiIIIII", data)
    kind = {6: "shared library", 2: "executable", 8: "bundle"}.get(filetype, f"filetype {filetype}")
    info = BinaryInfo("Mach-O", _MACHO_CPUS.get(cputype, f"cpu {cputype:#x}"), kind)
    trie = None
    symbols: set[str] = set()
    pos = 32
    for _ in range(ncmds):
        cmd, size = struct.unpack_from("<II", data, pos)
        if cmd in _LC_DYLIBS:
            (name_off,) = struct.unpack_from("<I", data, pos + 8)
            info.needs.append(_cstr(data, pos + name_off))
            if cmd != 0xC:
                info.extra.setdefault("special_dylibs", []).append(_LC_DYLIBS[cmd])
        elif cmd == _LC_ID_DYLIB:
            (name_off,) = struct.unpack_from("<I", data, pos + 8)
            info.extra["install_name"] = _cstr(data, pos + name_off)
        elif cmd == _LC_RPATH:
            (name_off,) = struct.unpack_from("<I", data, pos + 8)
            info.extra["runpath"] = _cstr(data, pos + name_off)
        elif cmd in (_LC_DYLD_INFO, _LC_DYLD_INFO_ONLY):
            export_off, export_size = struct.unpack_from("<II", data, pos + 40)
            if export_size:
                trie = (export_off, export_size)
        elif cmd == _LC_DYLD_EXPORTS_TRIE:
            trie = struct.unpack_from("<II", data, pos + 8)
        elif cmd == _LC_SYMTAB:
            symbols, info.imports = _macho_symtab(data, *struct.unpack_from("<IIII", data, pos + 8))
        elif cmd == _LC_BUILD_VERSION:
            platform, minos, _sdk = struct.unpack_from("<III", data, pos + 8)
            info.extra["platform"] = {1: "macos"}.get(platform, str(platform))
            info.extra["minos"] = _version(minos)
        elif cmd == _LC_VERSION_MIN_MACOSX:
            info.extra["platform"] = "macos"
            info.extra["minos"] = _version(struct.unpack_from("<I", data, pos + 8)[0])
        elif cmd == _LC_CODE_SIGNATURE:
            info.extra["signature"] = _macho_signature_check(data, *struct.unpack_from("<II", data, pos + 8))
        pos += size
    # dyld resolves symbols through the export trie; the symbol table's external definitions must agree
    exported = _macho_trie(data, *trie) if trie else symbols
    info.exports = {s.removeprefix("_") for s in exported}
    info.extra["symtab_exports"] = {s.removeprefix("_") for s in symbols}
    info.imports = {s.removeprefix("_") for s in info.imports}
    return info


def _macho_symtab(data: bytes, symoff: int, nsyms: int, stroff: int, _strsize: int) -> tuple[set, set]:
    defined, undefined = set(), set()
    for i in range(nsyms):
        n_strx, n_type, _sect, _desc, _value = struct.unpack_from("<IBBHQ", data, symoff + 16 * i)
        if n_type & 0xE0 or not n_type & 0x01:  # debug entries, or not external
            continue
        name = _cstr(data, stroff + n_strx)
        if (n_type & 0x0E) == 0x0E and not n_type & 0x10:  # N_SECT, not private-extern
            defined.add(name)
        elif (n_type & 0x0E) == 0:
            undefined.add(name)
    return defined, undefined


def _uleb(data: bytes, pos: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if byte < 0x80:
            return value, pos


def _macho_trie(data: bytes, start: int, size: int) -> set[str]:
    names: set[str] = set()
    seen: set[int] = set()
    todo = [(0, b"")]
    while todo:
        node, prefix = todo.pop()
        if node in seen or node >= size:
            raise FormatError("malformed export trie")
        seen.add(node)
        terminal, pos = _uleb(data, start + node)
        if terminal:
            names.add(prefix.decode())
        pos += terminal
        count = data[pos]
        pos += 1
        for _ in range(count):
            end = data.index(b"\0", pos)
            label = data[pos:end]
            child, pos = _uleb(data, end + 1)
            todo.append((child, prefix + label))
    return names


def _macho_signature_check(data: bytes, dataoff: int, datasize: int) -> str:
    """'valid' when the (ad-hoc) signature's code directory hashes every page of the file as it is,
    which Apple Silicon requires of all code it maps; otherwise what is wrong."""
    blob = data[dataoff:dataoff + datasize]
    magic, _length, count = struct.unpack_from(">III", blob)
    if magic != 0xFADE0CC0:
        return f"not a signature superblob ({magic:#x})"
    for i in range(count):
        _slot, offset = struct.unpack_from(">II", blob, 12 + 8 * i)
        if struct.unpack_from(">I", blob, offset)[0] != 0xFADE0C02:
            continue
        (_m, _len, _ver, _flags, hash_offset, _ident, _nspecial, ncode, code_limit, hash_size,
         hash_type, _platform, page_shift) = struct.unpack_from(">IIIIIIIIIBBBB", blob, offset)
        algorithm = {1: "sha1", 2: "sha256"}.get(hash_type)
        if algorithm is None:
            return f"hash type {hash_type}"
        page = 1 << page_shift
        for k in range(ncode):
            want = blob[offset + hash_offset + k * hash_size: offset + hash_offset + (k + 1) * hash_size]
            got = hashlib.new(algorithm, data[k * page: min((k + 1) * page, code_limit)]).digest()
            if got[:hash_size] != want:
                return f"page {k} hash mismatch"
        if ncode * page < code_limit:
            return "pages left unhashed"
        return "valid"
    return "no code directory"
