#!/usr/bin/env python3
"""Writes the fixtures of the safe pickle reader (`crates/formats/src/pickle/read.rs`,
`torch_zip/read.rs`) into
`crates/formats/tests/golden/`:

* `pickle_plain_p{0..5}.pkl`: one plain-data object (no tensors) pickled with protocols 0 to 5,
  and `pickle_plain_expected.json`: what each of them contains, as seen by CPython's own
  unpickler with every class replaced by a recording stub (so no class is imported and the
  opcode semantics - memo, marks, shared references, mutation after memoizing - are CPython's).
  The canonical form is documented in `canon` below; the Rust test builds the same form.
* `pickle_p2.pt` (torch.save default, protocol 2), `pickle_p4.pt` (`pickle_protocol=4`) and
  `pickle_p1.pt` (`pickle_protocol=1`, without the slots object and the cycle): a
  release-like checkpoint `{"model": state_dict, "meta_cfg": <custom config objects>}` with
  shared storages and views, int64 / float64 / float16 / bfloat16 / int32 / uint8 / bool tensors,
  nested OrderedDicts, a dict subclass, an EasyDict-like class, an object whose `__reduce__`
  returns a custom callable, a `__slots__` object, NEWOBJ_EX, sets and a reference cycle;
  `pickle_expected.safetensors` (`pickle_expected_p1.safetensors` for protocol 1): every tensor
  the reader must return, under its flattened key.
* `pickle_truncated.pt`, `pickle_garbled.pt`: valid zips whose `data.pkl` is cut in half or
  holds an unknown opcode.

Regenerate (from the repository root):  python3 tools/reference/pickle_fixtures.py
"""

import collections
import io
import json
import os
import pickle
import struct
import zipfile

import torch
from safetensors.torch import save_file

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..")
OUT = os.path.join(ROOT, "crates", "formats", "tests", "golden")


# ----------------------------------------------------------------------------------------------
# Classes standing in for a release's own config classes. The Rust reader never sees them, only
# their names in the pickle.


class ConfigDict(dict):
    """A dict subclass without attributes: NEWOBJ then SETITEMS."""


class EasyDictLike(dict):
    """Like `easydict.EasyDict`: every key is both an item and an attribute (BUILD state)."""

    def __init__(self, d=None, **kwargs):
        super().__init__()
        for k, v in {**(d or {}), **kwargs}.items():
            setattr(self, k, v)

    def __setattr__(self, name, value):
        if isinstance(value, dict) and not isinstance(value, EasyDictLike):
            value = EasyDictLike(value)
        super().__setattr__(name, value)
        super().__setitem__(name, value)

    __setitem__ = __setattr__


class Plain:
    """A plain object: NEWOBJ then BUILD with its `__dict__`."""

    def __init__(self, **kwargs):
        self.__dict__.update(kwargs)


class Slotted:
    """`__slots__` state pickles as the tuple `(None, {slot: value})`."""

    __slots__ = ("weight", "label")

    def __init__(self, weight, label):
        self.weight = weight
        self.label = label


_NEWARGS = {}


class WithKwargs:
    """`__getnewargs_ex__` gives NEWOBJ_EX in protocol 4 (a functools.partial REDUCE before).
    The arguments live outside `__dict__`, so they only appear as call arguments."""

    def __new__(cls, *args, **kwargs):
        return super().__new__(cls)

    def __init__(self, *args, **kwargs):
        _NEWARGS[id(self)] = (args, kwargs)
        self.label = "kw"

    def __getnewargs_ex__(self):
        return _NEWARGS[id(self)]


def make_custom(*args):
    """The custom callable of `Custom.__reduce__` (the Rust reader only records its name)."""
    return ConfigDict(args=args)


class Custom:
    """`__reduce__` returns a custom callable with args, a state dict and dict items."""

    def __init__(self, arg_tensor, state, items):
        self.arg_tensor = arg_tensor
        self.state = state
        self.items = items

    def __reduce__(self):
        return (make_custom, (self.arg_tensor, "arg"), self.state, None, iter(self.items))


class ListLike(list):
    """A list subclass: NEWOBJ then APPENDS."""


class Outer:
    class Inner(dict):
        """A nested class: protocols below 4 name it as `getattr(Outer, "Inner")`, a REDUCE."""


# ----------------------------------------------------------------------------------------------
# The oracle: CPython's unpickler with every global replaced by a stub that records what the
# opcodes do to it.


class Stub:
    _module = None
    _name = None

    def __new__(cls, *args, **kwargs):
        return Stub._record(object.__new__(cls), cls, args, kwargs)

    @staticmethod
    def _record(obj, callable_, args, kwargs):
        object.__setattr__(obj, "_rec", {"callable": callable_, "args": list(args),
                                          "kwargs": kwargs or None, "state": None,
                                          "items": [], "elems": []})
        return obj

    def __call__(self, *args, **kwargs):
        # REDUCE with a callable that is itself the result of a REDUCE (functools.partial).
        return Stub._record(object.__new__(CallResult), self, args, kwargs)

    def __init__(self, *args, **kwargs):
        pass

    def __setstate__(self, state):
        self._rec["state"] = state

    def __setitem__(self, key, value):
        self._rec["items"].append((key, value))

    def append(self, value):
        self._rec["elems"].append(value)

    def add(self, value):
        self._rec["elems"].append(value)


class CallResult(Stub):
    pass


class PersId:
    def __init__(self, pid):
        self.pid = pid


class StubUnpickler(pickle.Unpickler):
    def __init__(self, data):
        super().__init__(io.BytesIO(data))
        self.classes = {}

    def find_class(self, module, name):
        if name == "getattr" and module in ("builtins", "__builtin__"):
            # What getattr returns may be used as a class (NEWOBJ needs a real type).
            recorder = self.find_class(module, "getattr.")

            def make_class(*args):
                return type("GetattrResult", (Stub,), {"_call": (recorder, args)})
            return make_class
        key = (module, name)
        if key not in self.classes:
            self.classes[key] = type(name, (Stub,), {"_module": module, "_name": name})
        return self.classes[key]

    def persistent_load(self, pid):
        return PersId(pid)


def canon(x, ancestors=()):
    """Canonical JSON of an unpickled value. Shared subtrees are expanded; a value that is its
    own ancestor becomes {"cycle": null}. Ints and floats are strings (exact)."""
    if any(x is a for a in ancestors):
        return {"cycle": None}
    anc = ancestors + (x,)
    if x is None:
        return None
    if isinstance(x, bool):
        return x
    if isinstance(x, int):
        return {"int": str(x)}
    if isinstance(x, float):
        return {"float": struct.pack(">d", x).hex()}
    if isinstance(x, str):
        return x
    if isinstance(x, (bytes, bytearray)):
        return {"bytes": bytes(x).hex()}
    if isinstance(x, list):
        return {"list": [canon(v, anc) for v in x]}
    if isinstance(x, tuple):
        return {"tuple": [canon(v, anc) for v in x]}
    if isinstance(x, dict):
        return {"dict": [[canon(k, anc), canon(v, anc)] for k, v in x.items()]}
    if isinstance(x, (set, frozenset)):
        kind = "set" if isinstance(x, set) else "frozenset"
        items = [canon(v, anc) for v in x]
        return {kind: sorted(items, key=lambda c: json.dumps(c, sort_keys=True))}
    if isinstance(x, type) and issubclass(x, Stub) and "_call" in x.__dict__:
        fn, args = x._call
        return {"object": {"global": [fn._module, fn._name.rstrip(".")]},
                "args": [canon(v, anc) for v in args], "kwargs": None, "state": None,
                "items": [], "elems": []}
    if isinstance(x, type) and issubclass(x, Stub):
        return {"global": [x._module, x._name]}
    if isinstance(x, PersId):
        return {"persid": canon(x.pid, anc)}
    if isinstance(x, Stub):
        r = x._rec
        return {
            "object": canon(r["callable"], anc),
            "args": [canon(v, anc) for v in r["args"]],
            "kwargs": None if r["kwargs"] is None
            else [[k, canon(v, anc)] for k, v in r["kwargs"].items()],
            "state": canon(r["state"], anc),
            "items": [[canon(k, anc), canon(v, anc)] for k, v in r["items"]],
            "elems": [canon(v, anc) for v in r["elems"]],
        }
    raise TypeError(f"no canonical form for {type(x)}")


def plain_object(proto):
    shared = [1, 2, 3]
    cfg = ConfigDict(name="cfg", shared=shared)
    if proto >= 2:
        # Protocols 0-1 pickle a dict subclass through copyreg._reconstructor, which cannot
        # express a cycle, and cannot pickle __slots__ objects.
        cfg["self"] = cfg
    easy = EasyDictLike(lr=1e-4, steps=[1, 2], sub={"depth": 3})
    # A tuple reached again while it is being built: the pickler emits POP / POP_MARK.
    recursive_tuple = ([],)
    recursive_tuple[0].append(recursive_tuple)
    return {
        "none": None,
        "bools": [True, False],
        "ints": [0, 1, -1, 255, 256, 65535, 65536, -129, 2**31 - 1, -2**31, 2**31, 2**63 - 1,
                 -2**63, 2**64, -2**64 - 5, 12345678901234567890123456789],
        "floats": [0.0, -0.0, 1.5, 1e-300, -2.5e10, float("inf"), float("-inf"), 0.1],
        "strs": ["", "ascii", "naïve ünïcode ☃ 🙂", "quote ' and \" and \\ and \n newline",
                 "x" * 300],
        "bytes": [b"", b"\x00\x01\xff", bytes(range(256)), bytearray(b"mutable")],
        "tuples": [(), (1,), (1, 2), (1, 2, 3), (1, 2, 3, 4)],
        "nested": {"a": {"b": {"c": [{"d": ()}]}}},
        "od": collections.OrderedDict([("z", 1), ("a", collections.OrderedDict([("k", 2)]))]),
        "set": {1, 2, 3},
        "frozenset": frozenset({"a"}),
        "shared": (shared, shared),
        "cfg": cfg,
        "easy": easy,
        "plain": Plain(x=1, y="two"),
        "slotted": Slotted(None, "s") if proto >= 2 else None,
        "kwargs": WithKwargs(1, key="v"),
        "custom": Custom(None, {"st": 1}, [("it", 2)]),
        "listlike": ListLike([4, 5]),
        "nested_class": Outer.Inner(a=1),
        "class": ConfigDict,
        "func": make_custom,
        "recursive_tuple": recursive_tuple,
        "huge_int": -(2**3000) + 7,
        17: "int key",
        (1, 2): "tuple key",
    }


def u64(n):
    return struct.pack("<Q", n)


def framed(body):
    """A protocol 4 stream whose opcodes sit in one FRAME."""
    return b"\x80\x04\x95" + u64(len(body)) + body


# Opcodes CPython's pickler no longer emits (Python 2 strings, INST/OBJ, text PERSID, DUP, the
# 8-byte-length forms, extension codes, out-of-band buffers) and malformed streams, written by
# hand. `None` as expected value: CPython must refuse it, and so must the Rust reader.
HANDMADE = [
    ("py2_strings", b"(S'a\\\\b\\'c\\n\\x41\\101'\nS\"dq\"\nU\x03xyzT\x02\x00\x00\x00hil."),
    ("inst_obj", b"(K\x01K\x02imod\nCls\n(cmod\nOther\nK\x03o\x86."),
    ("persid_text", b"Pstorage 7\n."),
    ("dup_pop_popmark", b"]\x94(K\x01K\x022e(K\x05K\x061K\x070(0K\x08\x86."),
    ("long4", b"\x8b\x02\x00\x00\x00\xff\x7f."),
    ("long_text", b"(L-123456789012345678901234567890L\nL12L\nI-5\nI00\nF-1.25e-3\nl."),
    ("unicode_escapes", b"Vsnow \\u2603 smile \\U0001f642 latin \xe9\n."),
    ("len8_forms", framed(b"(\x8e" + u64(2) + b"\x00\x01\x8d" + u64(3) + "é!".encode()
                          + b"\x96" + u64(1) + b"zl.")),
    ("memo_forms", b"K\x05p7\nK\x06q\xc8K\x07r\x00\x00\x01\x00g7\nh\xc8j\x00\x00\x01\x00\x94\x87."),
    ("put_get_share", b"]p0\n(g0\ng0\nt\x94h\x00K\x01a0."),
    ("readonly_buffer", b"\x80\x05C\x02ab\x98."),
    ("ext1", None, b"\x80\x02\x82\x01."),
    ("next_buffer", None, b"\x80\x05\x97."),
    ("unknown_opcode", None, b"\x80\x02\xff."),
    ("no_stop", None, b"\x80\x02K\x01"),
    ("empty", None, b""),
    ("append_without_list", None, b"K\x01K\x02a."),
    ("appends_without_mark", None, b"]K\x01e."),
    ("pop_below_mark", None, b"](a."),
    ("stop_on_empty_mark", None, b"K\x01(."),
    ("get_missing", None, b"h\x03."),
    ("odd_setitems", None, b"}(K\x01u."),
    ("setitem_on_int", None, b"K\x01K\x02K\x03s."),
    ("bad_utf8_len", None, b"X\xff\x00\x00\x00ab."),
    ("negative_binstring", None, b"T\xff\xff\xff\xffab."),
    ("bad_proto", None, b"\x80\x06N."),
    ("stack_global_not_str", None, b"K\x01K\x02\x93."),
    ("bad_int_text", None, b"I12x\n."),
    ("frame_past_end", None, b"\x80\x04\x95\xff\x00\x00\x00\x00\x00\x00\x00N."),
]


def handmade_cases():
    cases = []
    for entry in HANDMADE:
        if len(entry) == 2:
            name, data = entry
            expected = canon(StubUnpickler(data).load())
            cases.append({"name": name, "hex": data.hex(), "expected": expected})
        else:
            name, _, data = entry
            try:
                StubUnpickler(data).load()
            except Exception as e:  # noqa: BLE001 - any refusal will do
                cases.append({"name": name, "hex": data.hex(), "error": repr(e)})
            else:
                raise AssertionError(f"CPython accepted the malformed case {name}")
    return cases


def write_plain():
    files = {}
    for proto in range(6):
        obj = plain_object(proto)
        data = pickle.dumps(obj, protocol=proto)
        name = f"pickle_plain_p{proto}.pkl"
        with open(os.path.join(OUT, name), "wb") as f:
            f.write(data)
        files[name] = canon(StubUnpickler(data).load())
    expected = {"files": files, "handmade": handmade_cases()}
    path = os.path.join(OUT, "pickle_plain_expected.json")
    with open(path, "w") as f:
        json.dump(expected, f, indent=None, separators=(",", ":"), sort_keys=True)
        f.write("\n")


# ----------------------------------------------------------------------------------------------
# Torch checkpoints.


def checkpoint(proto):
    """The checkpoint object and the tensors a reader must find in it, by flattened key.

    Reader policy (documented in pth.rs): the walk descends into dicts, OrderedDicts, dict- and
    list-like objects (SETITEMS / APPENDS items), lists and tuples (keys `0`, `1`, ...), and
    objects' BUILD state when it is a dict or a `(dict, slots dict)` tuple. It does not descend
    into REDUCE / NEWOBJ arguments (what an unknown callable makes of them is unknown) nor sets.
    Every tensor found is collected; a reference cycle is not followed. Protocols 0-1 pickle
    a dict / list subclass as `copyreg._reconstructor(cls, base, items)`: those items count.
    They cannot pickle `__slots__` objects or cycles through such subclasses, which are left
    out for them."""
    torch.manual_seed(0)
    module = torch.nn.Sequential(torch.nn.Linear(3, 2), torch.nn.BatchNorm1d(2))
    with torch.no_grad():
        module[1].running_mean.copy_(torch.tensor([0.25, -0.5]))
    module[1].num_batches_tracked.fill_(7)
    sd = module.state_dict()  # an OrderedDict with `_metadata` (BUILD state)

    # One float64 storage shared by four views with offsets, strides and a zero stride.
    base = torch.arange(48, dtype=torch.float64) * 0.1 - 1.3
    sd["views.flat"] = base
    sd["views.offset"] = base[5:17].view(3, 4)
    sd["views.strided"] = base.view(6, 8)[1:5, 2:7:2]
    sd["views.transposed"] = base.view(6, 8).t()
    sd["views.expanded"] = base[40:42].expand(3, 2)
    sd["dtypes.i64"] = torch.tensor([[-2**40, 3], [2**62, -1]], dtype=torch.int64)
    sd["dtypes.f16"] = torch.tensor([1.0, -0.333, 65504.0, 6e-8], dtype=torch.float16)
    sd["dtypes.bf16"] = torch.tensor([1.0, -3.14159, 1e30], dtype=torch.bfloat16)
    sd["dtypes.i32"] = torch.tensor([-7, 2**31 - 1], dtype=torch.int32)
    sd["dtypes.u8"] = torch.tensor([0, 200, 255], dtype=torch.uint8)
    sd["dtypes.bool"] = torch.tensor([True, False, True])
    sd["dtypes.scalar"] = torch.tensor(2.5)
    sd["dtypes.empty"] = torch.zeros(0, 3)
    sd["nested"] = collections.OrderedDict(
        a=collections.OrderedDict(b=collections.OrderedDict(c=torch.tensor([1.0, 2.0]))))
    sd["param"] = torch.nn.Parameter(torch.tensor([[0.5, -0.25]]))

    shared_f32 = module[0].weight.data  # the same storage as model.0.weight
    cfg = ConfigDict(
        NAME="GAGAvatar",
        TRAIN=EasyDictLike(lr=1e-4, steps=[1, 2], sub={"w": shared_f32[1]}),
        PLAIN=Plain(weight=torch.tensor([3.0, 4.0]), label="plain"),
        CUSTOM=Custom(torch.tensor([99.0]), {"state_t": torch.tensor([6.0])},
                      [("item_t", torch.tensor([7.0]))]),
        KW=WithKwargs(torch.tensor([98.0]), k=1),
        LIST=ListLike([torch.tensor([8.0])]),
        SEQ=[torch.tensor([9.0]), (torch.tensor([10.0]), "x")],
        SET={1, 2},
        FROZEN=frozenset({"f"}),
        INT_KEYS={0: torch.tensor([11.0]), 5: torch.tensor([12.0])},
        NESTED=Outer.Inner(t=torch.tensor([13.0])),
    )
    if proto >= 2:
        cfg["SLOTS"] = Slotted(torch.tensor([5.0]), "slots")
        cfg["SELF"] = cfg

    expected = {f"model.{k}": v for k, v in sd.items() if not isinstance(v, dict)}
    expected["model.nested.a.b.c"] = sd["nested"]["a"]["b"]["c"]
    expected.update({
        "meta_cfg.TRAIN.sub.w": shared_f32[1],
        "meta_cfg.PLAIN.weight": cfg["PLAIN"].weight,
        "meta_cfg.CUSTOM.state_t": cfg["CUSTOM"].state["state_t"],
        "meta_cfg.CUSTOM.item_t": cfg["CUSTOM"].items[0][1],
        "meta_cfg.LIST.0": cfg["LIST"][0],
        "meta_cfg.SEQ.0": cfg["SEQ"][0],
        "meta_cfg.SEQ.1.0": cfg["SEQ"][1][0],
        "meta_cfg.INT_KEYS.0": cfg["INT_KEYS"][0],
        "meta_cfg.INT_KEYS.5": cfg["INT_KEYS"][5],
        "meta_cfg.NESTED.t": cfg["NESTED"]["t"],
    })
    if proto >= 2:
        expected["meta_cfg.SLOTS.weight"] = cfg["SLOTS"].weight
    # Not expected: CUSTOM's REDUCE argument (99) and KW's NEWOBJ_EX argument (98).
    return {"model": sd, "meta_cfg": cfg}, expected


def rewrite_pickle(src, dst, edit):
    """Copies a torch zip, passing its data.pkl through `edit`."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_STORED) as zout:
        for info in zin.infolist():
            data = zin.read(info.filename)
            if info.filename.endswith("/data.pkl"):
                data = edit(data)
            zout.writestr(info, data)


def write_torch():
    for proto in (1, 2, 4):
        obj, expected = checkpoint(proto)
        path = os.path.join(OUT, f"pickle_p{proto}.pt")
        torch.save(obj, path, pickle_protocol=proto)
        # The file must round-trip in torch itself.
        back = torch.load(path, weights_only=False)
        assert torch.equal(back["model"]["views.strided"], obj["model"]["views.strided"])
        # The reader returns a bool tensor as its bytes (0 / 1); candle has no bool dtype.
        name = "pickle_expected.safetensors" if proto >= 2 else f"pickle_expected_p{proto}.safetensors"
        save_file({k: (v.to(torch.uint8) if v.dtype == torch.bool else v).detach().contiguous().clone()
                   for k, v in expected.items()},
                  os.path.join(OUT, name))
    p2 = os.path.join(OUT, "pickle_p2.pt")
    rewrite_pickle(p2, os.path.join(OUT, "pickle_truncated.pt"), lambda d: d[: len(d) // 2])
    # 0xff is no pickle opcode; put it where the next opcode is expected (after PROTO 2).
    rewrite_pickle(p2, os.path.join(OUT, "pickle_garbled.pt"), lambda d: d[:2] + b"\xff" + d[2:])


def main():
    os.makedirs(OUT, exist_ok=True)
    write_plain()
    write_torch()
    total = 0
    for name in sorted(os.listdir(OUT)):
        if name.startswith("pickle_"):
            size = os.path.getsize(os.path.join(OUT, name))
            total += size
            print(f"{name}: {size} bytes")
    print(f"total {total} bytes")


if __name__ == "__main__":
    main()
