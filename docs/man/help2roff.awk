# help2roff.awk: turns a --help text into man(7) source, so that a man page and the
# program's --help cannot drift apart (the help text in the C source is the one home).
#
# Usage: awk -v version="shapematch 0.1.0" -f help2roff.awk TEMPLATE.in HELP.txt > PAGE
#   TEMPLATE.in is man(7) source written by hand (NAME, DESCRIPTION, EXIT STATUS, ...);
#   its lines @SM_HELP@ and @SM_VERSION@ are replaced by the converted help text and by
#   `version`. Each line of HELP.txt becomes:
#     a line at column 0          -> a filled paragraph line (a blank line starts a new one)
#     a line indented by 2        -> a new .TP item: a command and its synopsis, or a
#                                    flag (and its value names) with its description;
#                                    several such lines of prose without a [ are one
#                                    indented paragraph instead
#     a deeper line opening with [ -> more of a command's synopsis (one that wraps)
#     any other deeper line       -> the body of the current item, filled
#   Option words (-k, --basis, ...) are set in bold; roff's special characters are escaped.

function esc(s) {
  gsub(/\\/, "\\e", s)
  gsub(/-/, "\\-", s)
  if (s ~ /^[.']/) s = "\\&" s
  return s
}

# Bold every word that starts with - or -- followed by a letter, at a word start (so the
# hyphen inside "non-isometric" is left alone). Works on the escaped text, where - is \-.
function bold_opts(s,    out, pre, m) {
  out = ""
  while (match(s, /(^|[ [(|,])(\\-\\-|\\-)[A-Za-z][A-Za-z0-9\\-]*/)) {
    pre = substr(s, 1, RSTART - 1)
    m = substr(s, RSTART, RLENGTH)
    if (m !~ /^\\/) { pre = pre substr(m, 1, 1); m = substr(m, 2) }
    out = out pre "\\fB" m "\\fR"
    s = substr(s, RSTART + RLENGTH)
  }
  return out s
}

function indent(s) { match(s, /^ */); return RLENGTH }

FNR == NR { tmpl[++nt] = $0; next }          # first file: the template
{ help[++nh] = $0 }

# The .TP tag of an item that opens with a flag: the flag, then its upper-case value
# names (--config FILE, --token TOKEN); the rest of the line starts the body. Nothing is
# dropped: the page must say all the help says (tests/install/test_manpages.sh).
function flag_tag(s,    n, w, i, tag) {
  n = split(s, w, " ")
  tag = w[1]
  if (tag ~ /:$/) i = 2                        # "--flag: text": the flag alone
  else for (i = 2; i <= n && w[i] ~ /^[A-Z]+$/; i++) tag = tag " " w[i]
  rest = ""
  for (; i <= n; i++) rest = rest (rest == "" ? "" : " ") w[i]
  return tag
}

function emit_help(    i, line, ind, text, in_tag, next_ind, tag) {
  in_tag = 0
  print ".nh"                                  # no hyphenation of option words,
  print ".ad l"                                # no stretched spaces
  print ".PP"
  for (i = 1; i <= nh; i++) {
    line = help[i]
    if (line ~ /^[ \t]*$/) { print ".PP"; in_tag = 0; continue }
    ind = indent(line)
    text = substr(line, ind + 1)
    next_ind = i < nh && help[i + 1] !~ /^[ \t]*$/ ? indent(help[i + 1]) : -1
    if (ind == 0) {
      if (in_tag) print ".PP"
      in_tag = 0
      print fmt(text)
    } else if (ind <= 2 && in_tag == 4) {       # more of that paragraph
      print fmt(text)
    } else if (ind <= 2 && text ~ /^-/) {       # a flag and its description
      tag = flag_tag(text)
      print ".TP"
      print fmt(tag)
      if (rest != "") print fmt(rest)
      in_tag = 3
    } else if (ind <= 2 && text !~ /\[/ && next_ind == ind) {
      if (in_tag != 4) print ".IP \"\" 2"      # prose set at the items' indent
      print fmt(text)
      in_tag = 4
    } else if (ind <= 2) {                      # a command and its synopsis
      print ".TP"
      print fmt(text)
      in_tag = 1
    } else if ((in_tag == 1 || in_tag == 2) && text ~ /^\[/) {
      print ".br"
      print fmt(text)
      in_tag = 2                               # the tag wrapped: its body needs a break
    } else {
      if (in_tag == 2) print ".br"
      if (in_tag == 1 || in_tag == 2) in_tag = 3
      print fmt(text)
    }
  }
  print ".ad b"
  print ".hy"
}

function fmt(s) { return bold_opts(esc(s)) }

END {
  for (i = 1; i <= nt; i++) {
    if (tmpl[i] == "@SM_HELP@") emit_help()
    else { line = tmpl[i]; gsub(/@SM_VERSION@/, version, line); print line }
  }
}
