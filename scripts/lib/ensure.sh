# Shared by the ensure-*.sh scripts: install a Debian package a test needs, or say how to.
#
#   ensure_package NAME PACKAGE CHECK WHY
#     CHECK is a shell function that succeeds once the package's programs are present.
#     Present: returns at once. Missing, as root: apt-get installs PACKAGE. Missing, not root:
#     prints how to install it; fails when CI=true (nothing may be skipped there), warns otherwise.

is_ci() {
    case "${CI:-}" in
        [Tt][Rr][Uu][Ee] | 1 | [Yy][Ee][Ss]) return 0 ;;
        *) return 1 ;;
    esac
}

ensure_package() {
    local name="$1" package="$2" check="$3" why="$4"
    if "$check"; then
        return 0
    fi
    if [[ "$(id -u)" -eq 0 ]]; then
        if ! command -v apt-get >/dev/null 2>&1; then
            echo "ensure-$name: $package is not installed and apt-get is not available; install it" \
                "with this system's package manager." >&2
            return 1
        fi
        echo "ensure-$name: installing $package (apt-get install $package) ..." >&2
        export DEBIAN_FRONTEND=noninteractive
        apt-get update -qq
        apt-get install -y -qq --no-install-recommends "$package" >/dev/null
        if ! "$check"; then
            echo "ensure-$name: 'apt-get install $package' finished but its programs are still missing." >&2
            return 1
        fi
        echo "ensure-$name: installed $package" >&2
        return 0
    fi
    local message="$package is not installed; $why Install it with:
  sudo apt-get install --no-install-recommends $package  (or run 'sudo bash $0')."
    if is_ci; then
        echo "ensure-$name: error: $message" >&2
        return 1
    fi
    echo "ensure-$name: warning: $message Those tests will be skipped." >&2
    return 0
}
