"""A cheaper Taichi frontend: source positions and function sources memoised.

Taichi 1.7 builds every kernel's IR by walking the Python AST of the kernel and of each ``ti.func``
it inlines (``ast_transformer_utils.Builder.__call__``). Before it builds *each* expression or
statement node, it formats that node's source position (``ASTTransformerContext.get_pos_info``: the
file, line, source line and a ``^^^`` hint, each run through ``textwrap.TextWrapper.wrap``) and
pushes it onto the runtime's debug-info stack, from where it is attached to the IR as the
statement's debug info and quoted in compile errors. Static unrolling and repeated inlining of a
``ti.func`` visit the same node many times, and the text wrapping is most of the frontend time:
about 6 of 10.7 s for the kernels of the Forming bench (docs/benchmarks_log.md), every process, with
Taichi's offline cache warm (the cache skips LLVM, not the AST walk, which produces the cache key).

:func:`memoize_source_positions` wraps that method so that a position already formatted in this
process is returned from a dictionary. The message depends only on the key used (the file, the
function's line offset and indentation, its name, the node's type, start and end line and column,
the first line of a compound statement's body, and the source lines quoted), so every message,
debug info and compile error stays character for character what Taichi produces (test).

:func:`memoize_function_sources` does the same for the source of each kernel and ``ti.func``:
Taichi reads it again (``inspect.getsourcelines``, which tokenises the file from the function's
first line) at every compilation of a kernel and at every inlining of a ``ti.func`` (about 1000
times for the Forming kernels). The memo is keyed by the Python function object and returns a copy
of the lines Taichi read the first time.
"""

from __future__ import annotations

import ast

_WRAPPED_FLAG = "_thinshell_memoized"
_COMPOUND = ("For", "While", "FunctionDef", "If")
"""Node types whose position message quotes the header lines only (as ``get_pos_info``)."""


def _position_key(ctx, node) -> tuple:
    """Everything ``get_pos_info(ctx, node)`` of Taichi 1.7.4 reads, as a hashable key (the quoted
    source lines: the node's lines, or for a compound statement its header lines)."""
    last = node.end_lineno
    first_body_line = None
    if type(node).__name__ in _COMPOUND:
        first_body_line = node.body[0].lineno
        last = max(first_body_line - 1, node.lineno)
    return (ctx.file, ctx.lineno_offset, ctx.indent, ctx.func.func.__name__, type(node).__name__, node.lineno,
            node.end_lineno, node.col_offset, node.end_col_offset, first_body_line,
            tuple(ctx.src[node.lineno - 1 : last]))


def memoize_source_positions() -> bool:
    """Memoise Taichi's per-node source-position messages in this process (module docstring).

    Idempotent. Only Taichi 1.7.x is patched (the version whose ``get_pos_info`` reads exactly
    the inputs of the key); for another version, or if the method is missing, nothing is changed.

    Returns:
        True when the memoised method is installed (now or by an earlier call), False otherwise.
    """
    import taichi  # optional heavy dependency: Taichi, loaded on a Taichi backend only
    from taichi.lang.ast import ast_transformer_utils

    context = getattr(ast_transformer_utils, "ASTTransformerContext", None)
    original = getattr(context, "get_pos_info", None)
    if original is None or tuple(taichi.__version__)[:2] != (1, 7):
        return False
    if getattr(original, _WRAPPED_FLAG, False):
        return True
    messages: dict[tuple, str] = {}

    def get_pos_info(self, node: ast.AST) -> str:
        key = _position_key(self, node)
        message = messages.get(key)
        if message is None:
            message = messages[key] = original(self, node)
        return message

    get_pos_info.__wrapped__ = original
    get_pos_info.__doc__ = "Taichi's ``get_pos_info``, memoised (sim_core.ti_frontend)."
    setattr(get_pos_info, _WRAPPED_FLAG, True)
    context.get_pos_info = get_pos_info
    return True


def memoize_function_sources() -> bool:
    """Memoise the source lines and file of each Taichi kernel / ``ti.func`` (module docstring).

    Patches the ``getsourcelines`` and ``getsourcefile`` that ``taichi.lang.kernel_impl`` calls
    (Taichi 1.7.x only; idempotent). A function's source is read once per process: edits to a
    source file while the process runs are not seen (as kernels already compiled are not rebuilt).

    Returns:
        True when the memoised functions are installed (now or by an earlier call), False otherwise.
    """
    import taichi  # optional heavy dependency: Taichi, loaded on a Taichi backend only
    from taichi.lang import kernel_impl

    lines_of, file_of = getattr(kernel_impl, "getsourcelines", None), getattr(kernel_impl, "getsourcefile", None)
    if lines_of is None or file_of is None or tuple(taichi.__version__)[:2] != (1, 7):
        return False
    if getattr(lines_of, _WRAPPED_FLAG, False):
        return True
    lines: dict = {}
    files: dict = {}

    def getsourcelines(obj):
        if obj not in lines:
            src, start = lines_of(obj)
            lines[obj] = (tuple(src), start)
        src, start = lines[obj]
        return list(src), start

    def getsourcefile(obj):
        if obj not in files:
            files[obj] = file_of(obj)
        return files[obj]

    for fn, original in ((getsourcelines, lines_of), (getsourcefile, file_of)):
        fn.__wrapped__ = original
        setattr(fn, _WRAPPED_FLAG, True)
    kernel_impl.getsourcelines = getsourcelines
    kernel_impl.getsourcefile = getsourcefile
    return True
